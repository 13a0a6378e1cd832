//! `rtu2mqtt check-config` and `rtu2mqtt check-templates`: validate files before a restart,
//! printing "ok" or each error with file, line:column and JSON path.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use crate::config::library::TemplateLibrary;
use crate::config::load::{load_config, DEFAULT_CONFIG_PATH};
use crate::config::{LocatedError, TemplateFile};
use crate::device::check_template;
use crate::device::configure::{resolve_config_checked, template_key_warnings};

#[derive(Debug, clap::Args)]
pub struct CheckConfigArgs {
    /// Config file.
    #[arg(short = 'c', long = "config", default_value = DEFAULT_CONFIG_PATH)]
    pub config: PathBuf,
    /// More template directories (searched after the system and user ones; later wins).
    #[arg(long = "templates", value_name = "DIR")]
    pub templates: Vec<PathBuf>,
    /// Treat warnings (misspelt keys, overrides the template does not allow) as errors.
    #[arg(long)]
    pub strict: bool,
}

#[derive(Debug, clap::Args)]
pub struct CheckTemplatesArgs {
    /// Template files or directories (default: the template search path).
    pub paths: Vec<PathBuf>,
}

pub fn run_check_config(args: CheckConfigArgs) -> anyhow::Result<ExitCode> {
    let loaded = match load_config(&args.config) {
        Ok(loaded) => loaded,
        Err(errors) => {
            for error in &errors.0 {
                println!("{error}");
            }
            return Ok(ExitCode::FAILURE);
        }
    };
    let mut dirs = loaded.config.template_dirs.clone();
    dirs.extend(args.templates.iter().cloned());
    let library = TemplateLibrary::load_standard(&dirs);
    let (result, warnings) = resolve_config_checked(&loaded, &library);
    for warning in &warnings {
        println!("{warning}");
    }
    if args.strict && !warnings.is_empty() && result.is_ok() {
        println!(
            "{}: {} warning(s), which --strict counts as errors",
            args.config.display(),
            warnings.len()
        );
        return Ok(ExitCode::FAILURE);
    }
    match result {
        Ok(ports) => {
            let devices: usize = ports.iter().map(|p| p.devices.len()).sum();
            let channels: usize = ports
                .iter()
                .flat_map(|p| &p.devices)
                .map(|d| d.channels.len())
                .sum();
            println!(
                "{}: ok ({} ports, {devices} devices, {channels} channels; {} templates)",
                args.config.display(),
                ports.len(),
                library.len()
            );
            Ok(ExitCode::SUCCESS)
        }
        Err(errors) => {
            for error in &errors.0 {
                println!("{error}");
            }
            Ok(ExitCode::FAILURE)
        }
    }
}

pub fn run_check_templates(args: CheckTemplatesArgs) -> anyhow::Result<ExitCode> {
    let paths = if args.paths.is_empty() {
        TemplateLibrary::standard_dirs(&[])
    } else {
        args.paths
    };
    let mut files = Vec::new();
    for path in &paths {
        if path.is_dir() {
            let mut found: Vec<PathBuf> = std::fs::read_dir(path)?
                .filter_map(Result::ok)
                .map(|e| e.path())
                .filter(|p| p.extension().is_some_and(|e| e == "json"))
                .collect();
            found.sort();
            files.extend(found);
        } else if path.exists() || !args_is_default(path) {
            files.push(path.clone());
        }
    }
    let mut failed = false;
    // device_type → (file, deprecated) of the first template seen with it.
    let mut seen: std::collections::BTreeMap<String, (PathBuf, bool)> = Default::default();
    for file in &files {
        let (template, errors) = check_file(file);
        if errors.is_empty() {
            println!("{}: ok", file.display());
        } else {
            failed = true;
            for error in errors {
                println!("{error}");
            }
        }
        let Some(template) = template else {
            continue;
        };
        let device_type = template.device_type().to_string();
        let deprecated = template.is_deprecated();
        match seen.get(&device_type) {
            None => {
                seen.insert(device_type, (file.clone(), deprecated));
            }
            Some((first, first_deprecated)) if *first_deprecated != deprecated => {
                let (used, unused) = if deprecated {
                    (first, file)
                } else {
                    (file, first)
                };
                println!(
                    "{}: note: device_type `{device_type}` is also defined in {}; the deprecated {} loses, {} is used",
                    file.display(),
                    first.display(),
                    unused.display(),
                    used.display()
                );
            }
            Some((first, _)) => {
                failed = true;
                println!(
                    "{}: device_type `{device_type}` is already defined in {}; only one is used (the later directory's, or the first file by name in one directory): remove or rename one",
                    file.display(),
                    first.display()
                );
            }
        }
    }
    if files.is_empty() {
        // Nothing checked is not a success: a wrong path must not look like a clean library.
        failed = true;
        println!(
            "no template files (*.json) found in {}",
            paths
                .iter()
                .map(|p| p.display().to_string())
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    Ok(if failed {
        ExitCode::FAILURE
    } else {
        ExitCode::SUCCESS
    })
}

fn args_is_default(path: &Path) -> bool {
    TemplateLibrary::standard_dirs(&[])
        .iter()
        .any(|d| d == path)
}

fn check_file(path: &Path) -> (Option<TemplateFile>, Vec<LocatedError>) {
    match TemplateFile::load(path) {
        Ok(template) => {
            let mut errors = check_template(&template);
            // Misspelt keys are reported, but do not fail the check (upstream files carry some).
            for warning in template_key_warnings(&template) {
                println!("{warning}");
            }
            errors.retain(|e| !matches!(e.problem, crate::config::error::Problem::Warning(_)));
            (Some(template), errors)
        }
        Err(error) => (None, vec![error]),
    }
}
