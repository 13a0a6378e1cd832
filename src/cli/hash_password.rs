//! `rtu2mqtt hash-password`: the bcrypt hash for the status page's `http.password_hash`.

use std::io::BufRead;
use std::process::ExitCode;

use anyhow::Context;

#[derive(clap::Args, Debug)]
pub struct Args {}

/// Reads the password from the first line of stdin (not from the command line, where `ps` and
/// the shell history would keep it) and prints its hash.
pub fn run(_args: Args) -> anyhow::Result<ExitCode> {
    use std::io::IsTerminal;
    if std::io::stdin().is_terminal() {
        eprintln!("password (shown as typed; end with Enter):");
    }
    let mut line = String::new();
    std::io::stdin()
        .lock()
        .read_line(&mut line)
        .context("cannot read the password from stdin")?;
    let password = line.trim_end_matches(['\r', '\n']);
    if password.is_empty() {
        eprintln!("empty password: give it on stdin, e.g. `printf '%s' 'secret' | rtu2mqtt hash-password`");
        return Ok(ExitCode::FAILURE);
    }
    let hash = crate::status::auth::hash_password(password).context("cannot hash the password")?;
    println!("{hash}");
    Ok(ExitCode::SUCCESS)
}
