//! `rtu2mqtt schema config|template`: the JSON Schemas, for editors and validators.

use std::process::ExitCode;

use crate::config::template::Template;

/// Which schema to print.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum SchemaKind {
    /// The config file.
    Config,
    /// Device templates.
    Template,
}

#[derive(Debug, clap::Args)]
pub struct SchemaArgs {
    /// `config` or `template`.
    #[arg(value_enum)]
    pub kind: SchemaKind,
}

/// The schema as JSON.
pub fn schema_json(kind: SchemaKind) -> serde_json::Value {
    match kind {
        SchemaKind::Config => crate::config::load::config_schema(),
        SchemaKind::Template => {
            serde_json::to_value(schemars::schema_for!(Template)).unwrap_or_default()
        }
    }
}

pub fn run(args: SchemaArgs) -> anyhow::Result<ExitCode> {
    println!("{}", serde_json::to_string_pretty(&schema_json(args.kind))?);
    Ok(ExitCode::SUCCESS)
}
