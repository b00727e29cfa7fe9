//! Encoding the results, each proven by readers we did not write: the texture writers (KTX2,
//! DDS, EXR, PNG), engine-ready textures, the streaming bake into PNG rows, PNG sizes, the
//! streamed assembly of tiled results, and the shader includes through real compilers.

#[path = "../support/mod.rs"]
mod support;

mod assembled;
mod encode;
mod png_sizes;
mod shaders;
mod stream;
mod textures;
