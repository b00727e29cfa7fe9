//! `horizon-bake bake` (SPEC §6). Not built yet: see the open issues.

/// Flags of `horizon-bake bake`.
#[derive(Debug, clap::Args)]
pub struct BakeArgs {}

/// Runs `horizon-bake bake`.
///
/// # Errors
/// Always, until this subcommand is built.
pub fn run(_args: BakeArgs) -> crate::Result<()> {
    Err(crate::Error::Internal("`bake` is not available in this build yet".into()))
}
