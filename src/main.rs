//! The `v2ce` command-line tool: parses the command line and runs the library's command
//! (`v2ce::cli`), reporting an error as one line and an exit status.

// Functions stay under 150 lines (clippy.toml): a longer one holds several steps to name.
#![warn(clippy::too_many_lines)]

use std::process::ExitCode;

use clap::Parser;

use v2ce::Error;

#[derive(Parser)]
#[command(
    name = "v2ce",
    version,
    about = "Video to continuous events: a DVS simulator (V2CE)"
)]
struct Cli {
    #[command(subcommand)]
    command: v2ce::cli::Command,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    // Every command logs its warnings (a guessed colour space, frames without exposure).
    init_logging();
    match cli.command.run() {
        Ok(()) => ExitCode::SUCCESS,
        Err(Error::Interrupted(why)) => {
            eprintln!("v2ce: interrupted: {why}");
            ExitCode::from(130)
        }
        Err(e) => {
            eprintln!("v2ce: error: {e}");
            ExitCode::FAILURE
        }
    }
}

/// Logs to stderr; under systemd (JOURNAL_STREAM set) without timestamps or colours, which the
/// journal adds or does not want. `V2CE_LOG` sets the level (error, warn, info, debug, trace).
fn init_logging() {
    use std::io::IsTerminal;
    let level = std::env::var("V2CE_LOG")
        .ok()
        .and_then(|l| l.parse::<tracing::Level>().ok())
        .unwrap_or(tracing::Level::INFO);
    let builder = tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        .with_max_level(level)
        .with_target(false);
    if std::env::var_os("JOURNAL_STREAM").is_some() {
        builder.without_time().with_ansi(false).init();
    } else {
        builder.with_ansi(std::io::stderr().is_terminal()).init();
    }
}
