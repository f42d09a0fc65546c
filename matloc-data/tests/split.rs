//! Split rules: nerfstudio's interval, test lists, and datasets that already have a split.

use std::path::PathBuf;

use matloc_core::{Camera, Pose};
use matloc_data::dataset::SceneMetadata;
use matloc_data::split::{SplitError, SplitRule, SplitSpec};
use matloc_data::{Dataset, Frame, Split};
use proptest::prelude::*;

/// Frames named `names`, in that (file) order, all train.
fn dataset(names: &[&str]) -> Dataset {
    let camera = Camera::pinhole(4, 3, 5.0, 5.0, 2.0, 1.5).unwrap();
    Dataset {
        root: PathBuf::from("/data"),
        frames: names
            .iter()
            .map(|n| Frame {
                image_path: PathBuf::from(n),
                depth_path: None,
                camera,
                cam_from_world: Pose::identity(),
                split: Split::Train,
            })
            .collect(),
        metadata: SceneMetadata::default(),
        points: None,
    }
}

fn test_names(ds: &Dataset) -> Vec<String> {
    ds.split(Split::Test)
        .map(|f| f.image_path.display().to_string())
        .collect()
}

#[test]
fn every_n_counts_from_the_first_frame_in_name_order() {
    // File order differs from name order; nerfstudio sorts by name, then takes i % n == 0.
    let mut ds = dataset(&[
        "c.png", "a.png", "e.png", "b.png", "d.png", "f.png", "g.png",
    ]);
    ds.apply_split(&SplitRule::Every(3)).unwrap();
    // Sorted: a b c d e f g → indices 0, 3, 6 = a, d, g.
    assert_eq!(test_names(&ds), ["a.png", "d.png", "g.png"]);
    assert_eq!(ds.split(Split::Train).count(), 4);
    // Frames stay in file order.
    assert_eq!(ds.frames[0].image_path, PathBuf::from("c.png"));
}

#[test]
fn every_needs_at_least_two() {
    let mut ds = dataset(&["a.png", "b.png"]);
    for n in [0, 1] {
        assert!(matches!(
            ds.apply_split(&SplitRule::Every(n)),
            Err(SplitError::BadInterval { .. })
        ));
    }
    // One frame: every 2nd leaves no training frame.
    let mut one = dataset(&["a.png"]);
    assert!(matches!(
        one.apply_split(&SplitRule::Every(2)),
        Err(SplitError::NoTrainFrames { frames: 1 })
    ));
    assert_eq!(
        one.frames[0].split,
        Split::Train,
        "nothing changes on error"
    );
}

#[test]
fn list_names_frames_by_path_or_unique_suffix() {
    let mut ds = dataset(&[
        "train/rgbs/000001.jpg",
        "val/rgbs/000002.jpg",
        "images/a/x.png",
        "images/b/x.png",
    ]);
    let rule = SplitRule::List(vec!["./val/rgbs/000002.jpg".into(), "a/x.png".into()]);
    ds.apply_split(&rule).unwrap();
    assert_eq!(test_names(&ds), ["val/rgbs/000002.jpg", "images/a/x.png"]);

    let mut ds2 = dataset(&["images/a/x.png", "images/b/x.png"]);
    let e = ds2
        .apply_split(&SplitRule::List(vec!["x.png".into()]))
        .unwrap_err();
    assert!(
        matches!(e, SplitError::AmbiguousEntry { count: 2, .. }),
        "{e}"
    );
    let e = ds2
        .apply_split(&SplitRule::List(vec!["images/c/x.png".into()]))
        .unwrap_err();
    assert!(matches!(e, SplitError::UnknownEntry { .. }), "{e}");
    assert!(e.to_string().contains("images/c/x.png"), "{e}");
}

#[test]
fn list_file_skips_blanks_and_comments() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("test.txt");
    std::fs::write(&p, "# held out\n\n  ./b.png \r\nc.png\n").unwrap();
    assert_eq!(
        SplitRule::read_list(&p).unwrap(),
        SplitRule::List(vec!["b.png".into(), "c.png".into()])
    );
    std::fs::write(&p, "# nothing\n").unwrap();
    assert!(matches!(
        SplitRule::read_list(&p),
        Err(SplitError::EmptyList { .. })
    ));
    assert!(matches!(
        SplitRule::read_list(&dir.path().join("missing.txt")),
        Err(SplitError::Io { .. })
    ));
}

#[test]
fn an_existing_split_is_kept_unless_resplit() {
    let mut ds = dataset(&["a.png", "b.png", "c.png", "d.png"]);
    ds.frames[1].split = Split::Test;
    ds.frames[2].split = Split::Val;
    let rule = SplitRule::Every(2);
    let e = ds.apply_split(&rule).unwrap_err();
    assert!(
        matches!(e, SplitError::AlreadySplit { test: 1, val: 1 }),
        "{e}"
    );
    assert_eq!(ds.frames[1].split, Split::Test, "nothing changes on error");
    SplitSpec {
        rule,
        resplit: true,
    }
    .apply(&mut ds)
    .unwrap();
    assert_eq!(test_names(&ds), ["a.png", "c.png"]);
    assert_eq!(ds.split(Split::Val).count(), 0);
}

#[test]
fn specs_serialise_as_tagged_rules() {
    let spec = SplitSpec {
        rule: SplitRule::Every(8),
        resplit: false,
    };
    let json = serde_json::to_value(&spec).unwrap();
    assert_eq!(
        json,
        serde_json::json!({"rule": {"every": 8}, "resplit": false})
    );
    let list: SplitSpec =
        serde_json::from_value(serde_json::json!({"rule": {"list": ["a.png"]}})).unwrap();
    assert_eq!(
        list,
        SplitSpec {
            rule: SplitRule::List(vec!["a.png".into()]),
            resplit: false
        }
    );
}

proptest! {
    #[test]
    fn every_n_picks_ceil_len_over_n(len in 2usize..60, n in 2usize..10) {
        let names: Vec<String> = (0..len).map(|i| format!("{:03}.png", (i * 37) % 1000)).collect();
        let refs: Vec<&str> = names.iter().map(String::as_str).collect();
        let mut ds = dataset(&refs);
        ds.apply_split(&SplitRule::Every(n)).unwrap();
        prop_assert_eq!(ds.split(Split::Test).count(), len.div_ceil(n));
        // The smallest name is always a test frame.
        let first = names.iter().min().unwrap();
        prop_assert!(test_names(&ds).contains(first));
    }
}
