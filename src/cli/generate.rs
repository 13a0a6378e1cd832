//! `rtu2mqtt completions SHELL` and `rtu2mqtt manpages DIR`: shell completions and man pages made
//! from the command-line definitions themselves, so they never drift from `--help`. The Debian
//! package runs both at build time.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use clap_complete::Shell;

#[derive(clap::Args)]
pub struct CompletionsArgs {
    /// bash, zsh, fish, elvish or powershell.
    pub shell: Shell,
}

#[derive(clap::Args)]
pub struct ManpagesArgs {
    /// Directory to write rtu2mqtt.1 and one rtu2mqtt-SUBCOMMAND.1 per subcommand into.
    pub dir: PathBuf,
}

/// Prints the completion script for `shell` on stdout.
pub fn completions(args: CompletionsArgs, mut command: clap::Command) -> anyhow::Result<ExitCode> {
    let name = command.get_name().to_owned();
    clap_complete::generate(args.shell, &mut command, name, &mut std::io::stdout());
    Ok(ExitCode::SUCCESS)
}

/// Writes the main page and one page per visible subcommand.
pub fn manpages(args: ManpagesArgs, command: clap::Command) -> anyhow::Result<ExitCode> {
    std::fs::create_dir_all(&args.dir)
        .with_context(|| format!("cannot create {}", args.dir.display()))?;
    let command = command.version(env!("CARGO_PKG_VERSION"));
    write_page(&args.dir, command.get_name(), command.clone())?;
    let parent = command.get_name().to_owned();
    for sub in command.get_subcommands().filter(|s| !s.is_hide_set()) {
        let name = format!("{parent}-{}", sub.get_name());
        let sub = sub
            .clone()
            .name(name.clone())
            .version(env!("CARGO_PKG_VERSION"));
        write_page(&args.dir, &name, sub)?;
    }
    Ok(ExitCode::SUCCESS)
}

fn write_page(dir: &std::path::Path, name: &str, command: clap::Command) -> anyhow::Result<()> {
    let path = dir.join(format!("{name}.1"));
    let mut page = Vec::new();
    clap_mangen::Man::new(command)
        .render(&mut page)
        .with_context(|| format!("cannot render the man page of {name}"))?;
    std::fs::write(&path, page).with_context(|| format!("cannot write {}", path.display()))
}
