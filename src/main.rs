//! The `horizon-bake` binary: parse the command line, call the library, map errors to an exit
//! code. Everything else lives in the library (see `src/lib.rs`).

use clap::Parser;
use std::process::ExitCode;

fn main() -> ExitCode {
    let cli = horizon_bake::cli::Cli::parse();
    match horizon_bake::cli::run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("horizon-bake: {e}");
            ExitCode::from(e.exit_code())
        }
    }
}
