//! Seeded network construction for the CNN backend (feature `burn`).
//!
//! The burn backend keeps one global random generator: `seed()` replaces it, and weight
//! initialisation draws from it when a parameter is first read (parameters are lazy). Two
//! trainings that build networks at once in one process (tests run in parallel, a server building
//! two maps) would interleave their draws, and the same seed would no longer give the same
//! weights. [`seeded_module`] seeds, builds and reads every parameter while holding one
//! process-wide lock, so each network's draws are its own.

use burn::module::{Module, ModuleVisitor, Param};
use burn::prelude::*;
use std::sync::Mutex;

static GENERATOR: Mutex<()> = Mutex::new(());

/// Seeds the backend's generator, builds a module with `build` and initialises all its float
/// parameters, under the process-wide lock.
pub fn seeded_module<M: Module>(device: &Device, seed: u64, build: impl FnOnce() -> M) -> M {
    // A panic inside another holder leaves nothing to repair: the generator is reseeded here
    // before anything draws.
    let _held = GENERATOR.lock().unwrap_or_else(|p| p.into_inner());
    device.seed(seed);
    let module = build();
    module.visit(&mut Materialise);
    module
}

/// Reads every float parameter, which runs its lazy initialiser.
struct Materialise;

impl ModuleVisitor for Materialise {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        let _ = param.val();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::nn::{Linear, LinearConfig};

    fn weights(seed: u64) -> Vec<f32> {
        let device = Device::flex();
        let l: Linear = seeded_module(&device, seed, || LinearConfig::new(256, 256).init(&device));
        l.weight.val().into_data().try_to_vec::<f32>().unwrap()
    }

    #[test]
    fn the_same_seed_gives_the_same_weights_while_others_build() {
        let reference = weights(7);
        // Other threads seed and build in between: the lock keeps the draws apart.
        let runs: Vec<Vec<f32>> = std::thread::scope(|s| {
            let hs: Vec<_> = (0..8)
                .map(|i| s.spawn(move || weights(if i % 2 == 0 { 7 } else { 8 })))
                .collect();
            hs.into_iter().map(|h| h.join().unwrap()).collect()
        });
        for (i, w) in runs.iter().enumerate() {
            if i % 2 == 0 {
                assert_eq!(w, &reference);
            } else {
                assert_ne!(w, &reference);
            }
        }
    }
}
