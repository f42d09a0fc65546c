//! Shared scene generation: the crate's own `synthetic` module.
#![allow(unused_imports)]

pub use matloc_pnp::synthetic::*;
