//! Tiled and distributed bakes: the tile decode (`streamed_tiles`), tiled bakes on one node
//! (`tiles`), and the distributed mode on the real engines (`distributed`, `distributed_tiles`:
//! PostgreSQL and an S3 server started by `scripts/engines.sh`). The engine tests take one lock,
//! `cluster::SERIAL`, so they run one at a time even though they share this process.

#[path = "../support/cluster.rs"]
mod cluster;
#[path = "../support/mod.rs"]
mod support;

mod distributed;
mod distributed_tiles;
mod streamed_tiles;
mod tiles;
