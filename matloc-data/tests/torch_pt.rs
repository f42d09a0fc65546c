//! `.pt` files: fixtures written by real `torch.save` (torch 2.15) read back exactly, round
//! trips through the writer, and bad input gives typed errors.

use std::path::{Path, PathBuf};

use matloc_data::torch_pt::{
    PtValue, Tensor, TensorData, TorchError, parse_pt, read_pt, to_pt_bytes, write_pt,
};
use proptest::prelude::*;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures/torch")
        .join(name)
}

fn tensor(v: &PtValue) -> &Tensor {
    match v {
        PtValue::Tensor(t) => t,
        other => panic!("expected a tensor, got {}", other.kind()),
    }
}

#[test]
fn reads_mega_nerf_metadata_written_by_torch() {
    let v = read_pt(&fixture("metadata.pt")).unwrap();
    assert_eq!(v.get("H"), Some(&PtValue::Int(3)));
    assert_eq!(v.get("W"), Some(&PtValue::Int(4)));
    let c2w = tensor(v.get("c2w").unwrap());
    assert_eq!(c2w.shape, vec![3, 4]);
    // torch.cat([camera_in_drb[:, 1:2], -camera_in_drb[:, :1], camera_in_drb[:, 2:4]], -1)
    assert_eq!(
        c2w.data,
        TensorData::F32(vec![
            1.0, -0.0, 0.0, 0.25, //
            0.0, -1.0, 0.0, -0.5, //
            0.0, -0.0, -1.0, 0.125
        ])
    );
    assert_eq!(
        tensor(v.get("intrinsics").unwrap()).data,
        TensorData::F32(vec![5.0, 6.0, 2.0, 1.5])
    );
    assert_eq!(
        tensor(v.get("distortion").unwrap()).data,
        TensorData::F32(vec![0.1, 0.0, 0.0, 0.0])
    );
}

#[test]
fn reads_coordinates_written_by_torch() {
    let v = read_pt(&fixture("coordinates.pt")).unwrap();
    let origin = tensor(v.get("origin_drb").unwrap());
    assert_eq!(origin.shape, vec![3]);
    assert_eq!(origin.to_f64(), vec![10.5, -3.25, 7.0]);
    assert_eq!(v.get("pose_scale_factor"), Some(&PtValue::Float(123.5)));
}

#[test]
fn reads_every_supported_type_written_by_torch() {
    let v = read_pt(&fixture("everything.pt")).unwrap();
    let keys: Vec<&str> = match &v {
        PtValue::Dict(items) => items.iter().map(|(k, _)| k.as_str()).collect(),
        other => panic!("{}", other.kind()),
    };
    assert_eq!(keys[..3], ["none", "yes", "no"], "file order is kept");
    assert_eq!(v.get("none"), Some(&PtValue::None));
    assert_eq!(v.get("yes"), Some(&PtValue::Bool(true)));
    assert_eq!(v.get("no"), Some(&PtValue::Bool(false)));
    let ints: Vec<PtValue> = [
        0,
        255,
        256,
        65535,
        65536,
        -1,
        -(1i64 << 31),
        1i64 << 31,
        1i64 << 40,
        i64::MIN,
        i64::MAX,
    ]
    .into_iter()
    .map(PtValue::Int)
    .collect();
    assert_eq!(v.get("ints"), Some(&PtValue::List(ints)));
    assert_eq!(
        v.get("floats"),
        Some(&PtValue::Tuple(vec![
            PtValue::Float(0.5),
            PtValue::Float(-1e-300),
            PtValue::Float(f64::INFINITY)
        ]))
    );
    assert_eq!(v.get("text"), Some(&PtValue::Str("Mill-19 é".into())));
    let nested = v.get("nested").unwrap();
    assert_eq!(
        nested.get("a"),
        Some(&PtValue::List(vec![
            PtValue::Int(1),
            PtValue::Tuple(vec![PtValue::Int(2), PtValue::Int(3)])
        ]))
    );
    assert_eq!(nested.get("b"), Some(&PtValue::Dict(vec![])));
    assert_eq!(
        v.get("size"),
        Some(&PtValue::Tuple(vec![PtValue::Int(4), PtValue::Int(6)]))
    );

    let big: Vec<f64> = (0..24).map(f64::from).collect();
    assert_eq!(tensor(v.get("f64").unwrap()), &Tensor::f64(vec![4, 6], big));
    // big[1:, ::2]: offset 6, strides (6, 2) into the shared storage.
    let view = tensor(v.get("view").unwrap());
    assert_eq!(view.shape, vec![3, 3]);
    assert_eq!(
        view.to_f64(),
        vec![6.0, 8.0, 10.0, 12.0, 14.0, 16.0, 18.0, 20.0, 22.0]
    );
    // big.t(): strides (1, 6).
    let t = tensor(v.get("transposed").unwrap());
    assert_eq!(t.shape, vec![6, 4]);
    assert_eq!(t.to_f64()[..5], [0.0, 6.0, 12.0, 18.0, 1.0]);
    assert_eq!(
        tensor(v.get("f32").unwrap()),
        &Tensor::f32(vec![2, 3], vec![1.0; 6])
    );
    assert_eq!(
        tensor(v.get("i32").unwrap()).data,
        TensorData::I32(vec![1, -2, 3, 4])
    );
    assert_eq!(
        tensor(v.get("i64").unwrap()).data,
        TensorData::I64(vec![-(1i64 << 62), 7])
    );
    assert_eq!(
        tensor(v.get("u8").unwrap()).data,
        TensorData::U8(vec![0, 128, 255])
    );
    let scalar = tensor(v.get("scalar").unwrap());
    assert!(scalar.shape.is_empty());
    assert_eq!(v.get("scalar").unwrap().as_f64(), Some(3.25));
    let empty = tensor(v.get("empty").unwrap());
    assert_eq!((empty.shape.clone(), empty.len()), (vec![0, 3], 0));
    assert_eq!(
        tensor(v.get("param").unwrap()),
        &Tensor::f32(vec![2], vec![1.5, 2.5])
    );
}

#[test]
fn legacy_torch_file_is_reported_as_legacy() {
    let e = read_pt(&fixture("legacy.pt")).unwrap_err();
    assert!(matches!(e, TorchError::LegacyFormat { .. }), "{e}");
    let msg = e.to_string();
    assert!(msg.contains("legacy.pt") && msg.contains("legacy"), "{msg}");
}

#[test]
fn missing_file_is_an_io_error_naming_it() {
    let e = read_pt(Path::new("/nonexistent/x.pt")).unwrap_err();
    assert!(matches!(e, TorchError::Io { .. }));
    assert!(e.to_string().contains("/nonexistent/x.pt"));
}

#[test]
fn writer_output_reads_back_and_fixtures_survive_a_rewrite() {
    let dir = tempfile::tempdir().unwrap();
    for name in ["metadata.pt", "coordinates.pt", "everything.pt"] {
        let v = read_pt(&fixture(name)).unwrap();
        let out = dir.path().join(name);
        write_pt(&out, &v).unwrap();
        assert_eq!(read_pt(&out).unwrap(), v, "{name}");
    }
}

/// A `.pt` archive with a hand-made pickle and storages.
fn archive(pickle: &[u8], storages: &[(&str, &[u8])]) -> Vec<u8> {
    use std::io::Write;
    let mut zip = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let options =
        zip::write::FileOptions::default().compression_method(zip::CompressionMethod::Stored);
    zip.start_file("archive/data.pkl", options).unwrap();
    zip.write_all(pickle).unwrap();
    for (key, bytes) in storages {
        zip.start_file(format!("archive/data/{key}"), options)
            .unwrap();
        zip.write_all(bytes).unwrap();
    }
    zip.finish().unwrap().into_inner()
}

/// A pickled 1-d tensor of `numel` float32 elements in storage `0`, with `offset` and `stride`.
fn tensor_pickle(storage: &str, numel: u8, size: u8, offset: u8, stride: u8) -> Vec<u8> {
    let mut p =
        b"\x80\x02ctorch._utils\n_rebuild_tensor_v2\n((X\x07\x00\x00\x00storagectorch\n".to_vec();
    p.extend_from_slice(storage.as_bytes());
    p.extend_from_slice(b"\nX\x01\x00\x00\x000X\x03\x00\x00\x00cpuK");
    p.extend_from_slice(&[
        numel, b't', b'Q', b'K', offset, b'K', size, 0x85, b'K', stride, 0x85,
    ]);
    p.extend_from_slice(b"\x89ccollections\nOrderedDict\n)RtR.");
    p
}

fn parse_err(bytes: &[u8], name: &str) -> TorchError {
    let e = parse_pt(bytes, Path::new(name)).unwrap_err();
    assert!(e.to_string().contains(name), "{e}");
    e
}

#[test]
fn hand_made_tensor_pickle_reads() {
    let data: Vec<u8> = (0..4).flat_map(|i| (i as f32).to_le_bytes()).collect();
    let v = parse_pt(
        &archive(&tensor_pickle("FloatStorage", 4, 2, 1, 2), &[("0", &data)]),
        Path::new("a.pt"),
    )
    .unwrap();
    assert_eq!(v, PtValue::Tensor(Tensor::f32(vec![2], vec![1.0, 3.0])));
}

#[test]
fn bad_pickles_and_storages_are_typed_errors_naming_the_file() {
    let data: Vec<u8> = (0..4).flat_map(|i| (i as f32).to_le_bytes()).collect();
    // A global that could run code.
    let e = parse_err(&archive(b"\x80\x02cos\nsystem\n.", &[]), "evil.pt");
    assert!(
        matches!(e, TorchError::Pickle { .. }) && e.to_string().contains("os.system"),
        "{e}"
    );
    // float16 storages are not read.
    let e = parse_err(
        &archive(&tensor_pickle("HalfStorage", 4, 2, 0, 1), &[("0", &data)]),
        "half.pt",
    );
    assert!(e.to_string().contains("HalfStorage"), "{e}");
    // The storage file is shorter than its element count.
    let e = parse_err(
        &archive(&tensor_pickle("FloatStorage", 5, 2, 0, 1), &[("0", &data)]),
        "short.pt",
    );
    assert!(matches!(e, TorchError::Storage { .. }), "{e}");
    // Offset and stride reach past the storage.
    let e = parse_err(
        &archive(&tensor_pickle("FloatStorage", 4, 2, 1, 3), &[("0", &data)]),
        "past.pt",
    );
    assert!(matches!(e, TorchError::Storage { .. }), "{e}");
    // The storage file is missing.
    let e = parse_err(
        &archive(&tensor_pickle("FloatStorage", 4, 2, 0, 1), &[]),
        "nostorage.pt",
    );
    assert!(matches!(e, TorchError::Storage { .. }), "{e}");
    // A dict with an int key.
    let e = parse_err(&archive(b"\x80\x02}(K\x01K\x02u.", &[]), "key.pt");
    assert!(e.to_string().contains("key"), "{e}");
    // Truncated pickle, unknown opcode, stack underflow, memo miss.
    for (pickle, name) in [
        (&b"\x80\x02X\xff\x00\x00\x00ab"[..], "trunc.pt"),
        (b"\x80\x02\xff.", "opcode.pt"),
        (b"\x80\x02t.", "mark.pt"),
        (b"\x80\x02a.", "under.pt"),
        (b"\x80\x02h\x05.", "memo.pt"),
    ] {
        let e = parse_err(&archive(pickle, &[]), name);
        assert!(matches!(e, TorchError::Pickle { .. }), "{e}");
    }
    // No data.pkl at all.
    let e = parse_err(&archive_without_pickle(), "empty.pt");
    assert!(matches!(e, TorchError::NotTorch { .. }), "{e}");
}

fn archive_without_pickle() -> Vec<u8> {
    use std::io::Write;
    let mut zip = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    zip.start_file("archive/version", zip::write::FileOptions::default())
        .unwrap();
    zip.write_all(b"3\n").unwrap();
    zip.finish().unwrap().into_inner()
}

#[test]
fn sizes_beyond_the_limits_are_refused_before_allocating() {
    // A storage of 2^40 elements is refused from its declared size alone.
    let mut p = tensor_pickle("FloatStorage", 4, 2, 0, 1);
    let at = p.windows(4).position(|w| w == b"cpuK").unwrap() + 3;
    p.splice(at..at + 2, *b"\x8a\x06\x00\x00\x00\x00\x00\x01");
    let e = parse_err(&archive(&p, &[]), "huge.pt");
    assert!(matches!(e, TorchError::TooLarge { .. }), "{e}");
}

#[test]
fn shared_references_cannot_blow_up_the_result() {
    // Level k is a list holding level k − 1 twice (through the memo): 2^40 leaves.
    let mut p = b"\x80\x02]q\x00".to_vec();
    for k in 1u8..=40 {
        p.extend_from_slice(&[b'(', b'h', k - 1, b'h', k - 1, b'l', b'q', k]);
    }
    p.push(b'.');
    let e = parse_err(&archive(&p, &[]), "bomb.pt");
    assert!(matches!(e, TorchError::TooLarge { .. }), "{e}");
    // A shared list is copied into both places.
    let p = b"\x80\x02](K\x01K\x02lq\x00h\x00\x86.";
    let v = parse_pt(&archive(p, &[]), Path::new("shared.pt")).unwrap();
    let inner = PtValue::List(vec![PtValue::Int(1), PtValue::Int(2)]);
    assert_eq!(v, PtValue::Tuple(vec![inner.clone(), inner]));
}

fn value_strategy() -> impl Strategy<Value = PtValue> {
    let leaf = prop_oneof![
        Just(PtValue::None),
        any::<bool>().prop_map(PtValue::Bool),
        any::<i64>().prop_map(PtValue::Int),
        any::<f64>()
            .prop_filter("NaN != NaN", |f| !f.is_nan())
            .prop_map(PtValue::Float),
        "[a-zA-Z0-9_é ]{0,12}".prop_map(PtValue::Str),
        (prop::collection::vec(1usize..4, 0..3)).prop_flat_map(|shape| {
            let n: usize = shape.iter().product();
            prop::collection::vec(-1e6..1e6f64, n)
                .prop_map(move |d| PtValue::Tensor(Tensor::f64(shape.clone(), d)))
        }),
        prop::collection::vec(any::<i32>(), 0..5).prop_map(|d| PtValue::Tensor(Tensor {
            shape: vec![d.len()],
            data: TensorData::I32(d)
        })),
    ];
    leaf.prop_recursive(3, 24, 4, |inner| {
        prop_oneof![
            prop::collection::vec(inner.clone(), 0..4).prop_map(PtValue::List),
            prop::collection::vec(inner.clone(), 0..4).prop_map(PtValue::Tuple),
            prop::collection::vec(("[a-z]{1,6}", inner), 0..4).prop_map(PtValue::Dict),
        ]
    })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn any_value_round_trips(v in value_strategy()) {
        let bytes = to_pt_bytes(&v, Path::new("p.pt")).unwrap();
        prop_assert_eq!(parse_pt(&bytes, Path::new("p.pt")).unwrap(), v);
    }
}

/// The pickle of a `.pt` file (its `data.pkl` entry).
fn pickle_of(bytes: &[u8]) -> Vec<u8> {
    use std::io::Read;
    let mut zip = zip::ZipArchive::new(std::io::Cursor::new(bytes)).unwrap();
    let name = zip
        .file_names()
        .find(|n| n.ends_with("/data.pkl"))
        .unwrap()
        .to_string();
    let mut out = Vec::new();
    zip.by_name(&name).unwrap().read_to_end(&mut out).unwrap();
    out
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    #[test]
    fn random_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..512)) {
        let _ = parse_pt(&bytes, Path::new("fuzz.pt"));
        let _ = parse_pt(&archive(&bytes, &[]), Path::new("fuzz.pt"));
    }

    #[test]
    fn truncated_files_are_errors(cut in any::<prop::sample::Index>()) {
        let bytes = std::fs::read(fixture("everything.pt")).unwrap();
        let n = cut.index(bytes.len());
        prop_assert!(parse_pt(&bytes[..n], Path::new("cut.pt")).is_err());
    }

    /// Mutated pickles of a torch-written file, re-archived with its storages so the zip
    /// layer accepts them: every result is a value or an error, never a panic.
    #[test]
    fn mutated_pickles_never_panic(
        edits in prop::collection::vec((any::<usize>(), any::<u8>(), 0u8..3), 1..6),
        which in 0usize..2,
    ) {
        let name = ["everything.pt", "metadata.pt"][which];
        let bytes = std::fs::read(fixture(name)).unwrap();
        let mut pickle = pickle_of(&bytes);
        for (pos, byte, kind) in edits {
            let i = pos % pickle.len().max(1);
            match kind {
                0 if !pickle.is_empty() => pickle[i] = byte,
                1 => pickle.insert(i.min(pickle.len()), byte),
                _ if !pickle.is_empty() => { pickle.remove(i); }
                _ => {}
            }
        }
        let storages: Vec<(String, Vec<u8>)> = {
            use std::io::Read;
            let mut zip = zip::ZipArchive::new(std::io::Cursor::new(&bytes[..])).unwrap();
            let names: Vec<String> = zip.file_names().filter(|n| n.contains("/data/")).map(String::from).collect();
            names.into_iter().map(|n| {
                let mut b = Vec::new();
                zip.by_name(&n).unwrap().read_to_end(&mut b).unwrap();
                (n.rsplit('/').next().unwrap().to_string(), b)
            }).collect()
        };
        let refs: Vec<(&str, &[u8])> = storages.iter().map(|(k, b)| (k.as_str(), b.as_slice())).collect();
        let _ = parse_pt(&archive(&pickle, &refs), Path::new("mutated.pt"));
    }
}
