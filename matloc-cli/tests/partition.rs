//! `matloc synth --preset tiny` then `matloc partition`, as a user would run them.

mod common;

use common::{matloc, text};

#[test]
fn synth_tiny_then_partition() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("tiny");
    let o = matloc(&["synth", "--preset", "tiny", "--out", data.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));

    let json = dir.path().join("pa.json");
    let png = dir.path().join("pa.png");
    let o = matloc(&[
        "partition",
        "--data",
        data.to_str().unwrap(),
        "--method",
        "pose-aware",
        "--target-size",
        "12",
        "--out",
        json.to_str().unwrap(),
        "--plot",
        png.to_str().unwrap(),
    ]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    assert!(
        t.contains("mean Num_NeRF(P): train 1.000, test 1.000"),
        "{t}"
    );
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    assert_eq!(v["method"], "pose-aware");
    assert_eq!(v["version"], 1);
    let blocks = v["blocks"].as_array().unwrap();
    let n = v["num_poses"].as_u64().unwrap() as usize;
    assert_eq!(blocks.len(), n.div_ceil(12));
    let mut ids: Vec<u64> = blocks
        .iter()
        .flat_map(|b| {
            b["pose_ids"]
                .as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_u64().unwrap())
        })
        .collect();
    ids.sort_unstable();
    ids.dedup();
    assert_eq!(ids.len(), n, "every pose in exactly one block");
    for b in blocks {
        assert!(b["sampling_volume_m3"].as_f64().unwrap() > 0.0);
    }
    let img = image::open(&png).expect("plot decodes");
    assert!(img.width() >= 800 && img.height() >= 600);

    // The grid baseline with the default plot path next to the JSON.
    let gjson = dir.path().join("grid.json");
    let o = matloc(&[
        "partition",
        "--data",
        data.to_str().unwrap(),
        "--method",
        "grid",
        "--grid",
        "2x2",
        "--out",
        gjson.to_str().unwrap(),
    ]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&gjson).unwrap()).unwrap();
    assert_eq!(v["method"], "grid");
    assert_eq!(v["blocks"].as_array().unwrap().len(), 4);
    assert!(image::open(dir.path().join("grid.png")).is_ok());

    // Bad input is reported, not a panic.
    let o = matloc(&[
        "partition",
        "--data",
        data.to_str().unwrap(),
        "--method",
        "grid",
        "--grid",
        "0x3",
    ]);
    assert!(!o.status.success());
    assert!(text(&o).contains("--grid"), "{}", text(&o));

    // Place predictor on the same data: a short training run, then the Table 4 evaluation.
    let model = dir.path().join("place");
    let o = matloc(&[
        "place",
        "train",
        "--data",
        data.to_str().unwrap(),
        "--epochs",
        "2",
        "--partition",
        json.to_str().unwrap(),
        "--out",
        model.to_str().unwrap(),
    ]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    assert!(t.contains("pose groups"), "{t}");
    assert!(model.join("place.json").is_file() && model.join("place.safetensors").is_file());
    let v: serde_json::Value =
        serde_json::from_slice(&std::fs::read(model.join("place.json")).unwrap()).unwrap();
    assert!(
        v["groups"]["groups"]
            .as_array()
            .unwrap()
            .iter()
            .all(|g| g["block"].is_u64())
    );
    let o = matloc(&[
        "place",
        "eval",
        "--data",
        data.to_str().unwrap(),
        "--model",
        model.to_str().unwrap(),
    ]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    assert!(t.contains("top-1") && t.contains("ArcFace"), "{t}");
}
