//! Studies behind matloc-nerf's design decisions and benchmark figures, as examples
//! (`cargo run --release -p matloc-research --example NAME -- ARGS`); this library is empty.
