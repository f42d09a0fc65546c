//! Writes seeded random feature sets as `.npy` and times the tiled MNN and the materialised
//! faer baseline on them, for `bench/match/compare.py` to run torch on the same input.
//!
//! Usage: `mnn_peer OUT_DIR [N] [DIMS,..] [REPS]`

use matloc_match::kernel::{nn_tables_faer, nn_tables_tiled};
use matloc_match::{MnnConfig, NnTables, mutual_from_tables};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::time::Instant;

fn unit_rows(rng: &mut ChaCha8Rng, n: usize, d: usize) -> Vec<f32> {
    let mut v: Vec<f32> = (0..n * d).map(|_| rng.random_range(-1.0f32..1.0)).collect();
    for row in v.chunks_exact_mut(d) {
        let norm = row.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-6);
        row.iter_mut().for_each(|x| *x /= norm);
    }
    v
}

/// `data` as a `rows × cols` little-endian f32 `.npy` array, C order.
fn write_npy(
    path: &std::path::Path,
    data: &[f32],
    rows: usize,
    cols: usize,
) -> std::io::Result<()> {
    use npyz::WriterBuilder;
    let file = std::io::BufWriter::new(std::fs::File::create(path)?);
    // Little-endian whatever the host.
    let dtype = npyz::DType::new_scalar("<f4".parse().expect("a valid type string"));
    let mut writer = npyz::WriteOptions::<f32>::new()
        .dtype(dtype)
        .shape(&[rows as u64, cols as u64])
        .writer(file)
        .begin_nd()?;
    writer.extend(data.iter().copied())?;
    writer.finish()
}

fn median_ms(reps: usize, mut f: impl FnMut() -> NnTables) -> (f64, NnTables) {
    let mut t = Vec::with_capacity(reps);
    let mut last = f();
    for _ in 0..reps {
        let s = Instant::now();
        last = f();
        t.push(s.elapsed().as_secs_f64() * 1e3);
    }
    t.sort_by(f64::total_cmp);
    (t[t.len() / 2], last)
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let out = std::path::PathBuf::from(
        args.get(1)
            .map(String::as_str)
            .unwrap_or("target-match/bench-match"),
    );
    let n: usize = args.get(2).map(|s| s.parse()).transpose()?.unwrap_or(4800);
    let dims: Vec<usize> = args
        .get(3)
        .map(|s| s.split(',').map(|x| x.parse()).collect::<Result<_, _>>())
        .transpose()?
        .unwrap_or_else(|| vec![5, 10, 15, 32, 47]);
    let reps: usize = args.get(4).map(|s| s.parse()).transpose()?.unwrap_or(15);
    std::fs::create_dir_all(&out)?;
    let threads = rayon::current_num_threads();
    let mut json = String::from("[\n");
    for (k, &d) in dims.iter().enumerate() {
        let mut rng = ChaCha8Rng::seed_from_u64(1000 + d as u64);
        let q = unit_rows(&mut rng, n, d);
        let m = unit_rows(&mut rng, n, d);
        write_npy(&out.join(format!("query_{d}.npy")), &q, n, d)?;
        write_npy(&out.join(format!("map_{d}.npy")), &m, n, d)?;
        let (tiled_ms, t) = median_ms(reps, || nn_tables_tiled(&q, n, &m, n, d, false));
        let (tiled2_ms, _) = median_ms(reps, || nn_tables_tiled(&q, n, &m, n, d, true));
        let (faer_ms, f) = median_ms(reps.min(5), || nn_tables_faer(&q, n, &m, n, d));
        let cfg = MnnConfig::default();
        let mt = mutual_from_tables(&t, &cfg);
        let mf = mutual_from_tables(&f, &cfg);
        let gflops = 2.0 * (n * n * d) as f64 / (tiled_ms * 1e-3) / 1e9;
        println!(
            "D={d:2}: tiled {tiled_ms:7.2} ms ({gflops:5.1} GFLOP/s), tiled+second {tiled2_ms:7.2} ms, faer materialised {faer_ms:7.2} ms, MNN matches {} (faer {})",
            mt.len(),
            mf.len()
        );
        json.push_str(&format!(
            "  {{\"d\": {d}, \"n\": {n}, \"threads\": {threads}, \"tiled_ms\": {tiled_ms}, \"tiled_second_ms\": {tiled2_ms}, \"faer_ms\": {faer_ms}, \"mnn_matches\": {}, \"mnn_pairs\": [{}]}}{}\n",
            mt.len(),
            mt.iter().take(20).map(|x| format!("[{}, {}]", x.query, x.map)).collect::<Vec<_>>().join(", "),
            if k + 1 < dims.len() { "," } else { "" }
        ));
    }
    json.push_str("]\n");
    std::fs::write(out.join("rust.json"), json)?;
    Ok(())
}
