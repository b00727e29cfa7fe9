//! `horizon-bake serve` (SPEC §6). Not built yet: see the open issues.

/// Flags of `horizon-bake serve`.
#[derive(Debug, clap::Args)]
pub struct ServeArgs {}

/// Runs `horizon-bake serve`.
///
/// # Errors
/// Always, until this subcommand is built.
pub fn run(_args: ServeArgs) -> crate::Result<()> {
    Err(crate::Error::Internal("`serve` is not available in this build yet".into()))
}
