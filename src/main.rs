//! The `horizon-bake` binary: parse the command line, call the library, map errors to an exit
//! code. Everything else lives in the library (see `src/lib.rs`).

use clap::Parser;
use std::process::ExitCode;

fn main() -> ExitCode {
    let cli = match horizon_bake::cli::Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) => {
            use clap::error::ErrorKind;
            if matches!(e.kind(), ErrorKind::DisplayHelp | ErrorKind::DisplayVersion)
                || e.kind() == ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand
            {
                e.exit();
            }
            // SPEC §6: one clear line on stderr.
            eprintln!("horizon-bake: {}", horizon_bake::cli::usage_error_line(&e));
            return ExitCode::from(2);
        }
    };
    match horizon_bake::cli::run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("horizon-bake: {e}");
            ExitCode::from(e.exit_code())
        }
    }
}
