//! Criterion benches (placeholder until the solvers land).
fn main() {}
