//! Cross-crate end-to-end tests of matloc-nerf; the tests live in `tests/`, this library is
//! empty.
