//! `horizon-bake shaders -o DIR` (SPEC §6, §8): writes the shader includes, their examples and
//! the engine wrappers (see [`crate::shaders`]). Written all or nothing, like `bake`.

use crate::error::Result;
use std::path::PathBuf;

/// Flags of `horizon-bake shaders`.
#[derive(Debug, Clone, clap::Args)]
pub struct ShadersArgs {
    /// Output directory (created if missing).
    #[arg(short = 'o', long = "out")]
    pub out: PathBuf,
}

/// Runs `horizon-bake shaders`.
///
/// # Errors
/// [`crate::Error::Io`] (or [`crate::Error::Param`] naming `out` when DIR is a file) when DIR
/// cannot be written; DIR is then left as it was.
pub fn run(args: ShadersArgs) -> Result<()> {
    super::bake::write_dir_atomically(&args.out, &crate::shaders::out_files())
}
