//! `horizon-bake eval` (SPEC §6). Not built yet: see the open issues.

/// Flags of `horizon-bake eval`.
#[derive(Debug, clap::Args)]
pub struct EvalArgs {}

/// Runs `horizon-bake eval`.
///
/// # Errors
/// Always, until this subcommand is built.
pub fn run(_args: EvalArgs) -> crate::Result<()> {
    Err(crate::Error::Internal("`eval` is not available in this build yet".into()))
}
