//! Random, truncated and mutated bytes never make a reader panic: they parse or return an error.

use std::path::Path;
use std::sync::OnceLock;

use matloc_data::Split;
use matloc_data::colmap::{
    ColmapFormat, parse_cameras_binary, parse_cameras_text, parse_images_binary, parse_images_text,
    parse_points3d_binary, parse_points3d_text, read_colmap, write_colmap,
};
use matloc_data::images::{encode_npy_f32, parse_npy};
use matloc_data::nerfstudio::parse_transforms;
use matloc_data::ply::{parse_ply, ply_bytes};
use matloc_data::torch_pt::parse_pt;
use nalgebra::Point3;
use proptest::prelude::*;

fn fixture_bytes(rel: &str) -> Vec<u8> {
    std::fs::read(
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("tests/fixtures")
            .join(rel),
    )
    .unwrap()
}

/// Valid inputs of every format: the corpus that mutations start from.
struct Corpus {
    transforms: Vec<Vec<u8>>,
    cameras_txt: Vec<u8>,
    images_txt: Vec<u8>,
    points_txt: Vec<u8>,
    cameras_bin: Vec<u8>,
    images_bin: Vec<u8>,
    points_bin: Vec<u8>,
    npy: Vec<u8>,
    ply_ascii: Vec<u8>,
    ply_binary: Vec<u8>,
    pt: Vec<u8>,
}

fn corpus() -> &'static Corpus {
    static CORPUS: OnceLock<Corpus> = OnceLock::new();
    CORPUS.get_or_init(|| {
        let model =
            read_colmap(&Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/colmap_text"))
                .unwrap();
        let dir = tempfile::tempdir().unwrap();
        write_colmap(&model, dir.path(), ColmapFormat::Binary).unwrap();
        let bin = |n: &str| std::fs::read(dir.path().join(n)).unwrap();
        Corpus {
            transforms: vec![
                fixture_bytes("ns_global/transforms.json"),
                fixture_bytes("ns_per_frame/transforms.json"),
                fixture_bytes("blender/transforms_train.json"),
            ],
            cameras_txt: fixture_bytes("colmap_text/sparse/0/cameras.txt"),
            images_txt: fixture_bytes("colmap_text/sparse/0/images.txt"),
            points_txt: fixture_bytes("colmap_text/sparse/0/points3D.txt"),
            cameras_bin: bin("cameras.bin"),
            images_bin: bin("images.bin"),
            points_bin: bin("points3D.bin"),
            npy: encode_npy_f32(3, 2, &[0.0, 1.0, 2.0, 3.0, 4.0, 5.0]),
            ply_ascii: b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\n\
                         property float y\nproperty float z\nproperty uchar red\n\
                         property uchar green\nproperty uchar blue\nelement face 1\n\
                         property list uchar int vertex_indices\nend_header\n\
                         1 2 3 4 5 6\n-1 0.5 2e1 7 8 9\n3 0 1 1\n"
                .to_vec(),
            ply_binary: ply_bytes(
                &[Point3::new(1.0, 2.0, 3.0), Point3::new(-4.0, 5.5, 6.25)],
                None,
            ),
            pt: fixture_bytes("torch/metadata.pt"),
        }
    })
}

/// Applies byte edits: (position, new byte, kind) with kind 0 = overwrite, 1 = insert,
/// 2 = delete; positions wrap around the current length.
fn mutate(mut bytes: Vec<u8>, edits: &[(usize, u8, u8)]) -> Vec<u8> {
    for &(pos, byte, kind) in edits {
        if bytes.is_empty() {
            bytes.push(byte);
            continue;
        }
        let i = pos % bytes.len();
        match kind % 3 {
            0 => bytes[i] = byte,
            1 => bytes.insert(i, byte),
            _ => {
                bytes.remove(i);
            }
        }
    }
    bytes
}

/// Bytes that matter to the parsers: structure characters, digits, NUL, 0xFF.
fn interesting_byte() -> impl Strategy<Value = u8> {
    prop_oneof![
        any::<u8>(),
        prop::sample::select(b"{}[]\",:.-+eE0123456789 \n#\0\xffNaI".to_vec()),
    ]
}

fn edits() -> impl Strategy<Value = Vec<(usize, u8, u8)>> {
    prop::collection::vec((any::<usize>(), interesting_byte(), any::<u8>()), 1..8)
}

fn run_all(bytes: &[u8]) {
    let p = Path::new("fuzz");
    let _ = parse_transforms(bytes, p, Path::new("/nonexistent-root"), Split::Train);
    let _ = parse_cameras_text(bytes, p);
    let _ = parse_images_text(bytes, p);
    let _ = parse_points3d_text(bytes, p);
    let _ = parse_cameras_binary(bytes, p);
    let _ = parse_images_binary(bytes, p);
    let _ = parse_points3d_binary(bytes, p);
    let _ = parse_npy(bytes);
    let _ = parse_ply(bytes, p);
    let _ = parse_pt(bytes, p);
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, ..ProptestConfig::default() })]

    #[test]
    fn random_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..512)) {
        run_all(&bytes);
    }

    #[test]
    fn truncated_inputs_are_errors(cut in any::<prop::sample::Index>()) {
        let c = corpus();
        let p = Path::new("fuzz");
        for t in &c.transforms {
            // Only the trailing newline may go without breaking the document.
            let n = cut.index(t.trim_ascii_end().len());
            prop_assert!(parse_transforms(&t[..n], p, Path::new("/nonexistent-root"), Split::Train).is_err());
        }
        // Binary files have no slack: every strict prefix is an error.
        for (bytes, which) in [(&c.cameras_bin, 0), (&c.images_bin, 1), (&c.points_bin, 2)] {
            let n = cut.index(bytes.len());
            let err = match which {
                0 => parse_cameras_binary(&bytes[..n], p).is_err(),
                1 => parse_images_binary(&bytes[..n], p).is_err(),
                _ => parse_points3d_binary(&bytes[..n], p).is_err(),
            };
            prop_assert!(err, "prefix of {n} bytes parsed");
        }
        let n = cut.index(c.npy.len());
        prop_assert!(parse_npy(&c.npy[..n]).is_err());
        // Text prefixes may be valid (a cut at a line end); they only must not panic.
        for t in [&c.cameras_txt, &c.images_txt, &c.points_txt] {
            run_all(&t[..cut.index(t.len())]);
        }
    }

    #[test]
    fn mutated_transforms_never_panic(which in 0usize..3, e in edits()) {
        let c = corpus();
        let bytes = mutate(c.transforms[which].clone(), &e);
        let _ = parse_transforms(&bytes, Path::new("fuzz"), Path::new("/nonexistent-root"), Split::Train);
    }

    #[test]
    fn mutated_colmap_never_panics(e in edits()) {
        let c = corpus();
        let p = Path::new("fuzz");
        let _ = parse_cameras_text(&mutate(c.cameras_txt.clone(), &e), p);
        let _ = parse_images_text(&mutate(c.images_txt.clone(), &e), p);
        let _ = parse_points3d_text(&mutate(c.points_txt.clone(), &e), p);
        let _ = parse_cameras_binary(&mutate(c.cameras_bin.clone(), &e), p);
        let _ = parse_images_binary(&mutate(c.images_bin.clone(), &e), p);
        let _ = parse_points3d_binary(&mutate(c.points_bin.clone(), &e), p);
    }

    #[test]
    fn mutated_npy_never_panics(e in edits()) {
        let _ = parse_npy(&mutate(corpus().npy.clone(), &e));
    }

    #[test]
    fn mutated_ply_and_torch_files_never_panic(e in edits(), cut in any::<prop::sample::Index>()) {
        let c = corpus();
        let p = Path::new("fuzz");
        let _ = parse_ply(&mutate(c.ply_ascii.clone(), &e), p);
        let _ = parse_ply(&mutate(c.ply_binary.clone(), &e), p);
        let _ = parse_pt(&mutate(c.pt.clone(), &e), p);
        // Every strict prefix of the binary PLY and of the torch archive is an error.
        prop_assert!(parse_ply(&c.ply_binary[..cut.index(c.ply_binary.len())], p).is_err());
        prop_assert!(parse_pt(&c.pt[..cut.index(c.pt.len())], p).is_err());
        let _ = parse_ply(&c.ply_ascii[..cut.index(c.ply_ascii.len())], p);
    }
}
