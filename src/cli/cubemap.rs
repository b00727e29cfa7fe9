//! `horizon-bake cubemap` (SPEC §6). Not built yet: see the open issues.

/// Flags of `horizon-bake cubemap`.
#[derive(Debug, clap::Args)]
pub struct CubemapArgs {}

/// Runs `horizon-bake cubemap`.
///
/// # Errors
/// Always, until this subcommand is built.
pub fn run(_args: CubemapArgs) -> crate::Result<()> {
    Err(crate::Error::Internal("`cubemap` is not available in this build yet".into()))
}
