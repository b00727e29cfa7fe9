//! `horizon-bake preview` (SPEC §6). Not built yet: see the open issues.

/// Flags of `horizon-bake preview`.
#[derive(Debug, clap::Args)]
pub struct PreviewArgs {}

/// Runs `horizon-bake preview`.
///
/// # Errors
/// Always, until this subcommand is built.
pub fn run(_args: PreviewArgs) -> crate::Result<()> {
    Err(crate::Error::Internal("`preview` is not available in this build yet".into()))
}
