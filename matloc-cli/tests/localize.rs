//! `matloc localize` argument handling, run as a user would; checks that need no map fail
//! before the map is opened. The batch and the pose formats are unit-tested in the crate.

mod common;

use common::{matloc, text};

#[test]
fn localize_flags_are_checked_before_the_map_loads() {
    let dir = tempfile::tempdir().unwrap();
    let list = dir.path().join("queries.txt");
    std::fs::write(&list, "a.png PINHOLE 32 24 30 30 16 12\n").unwrap();
    let (list, images) = (list.to_str().unwrap(), dir.path().to_str().unwrap());
    let map = "/definitely/not/a/map";
    let base = ["localize", "--map", map];

    let cases: [(&[&str], &str); 5] = [
        (&["--images", images, "--format", "nerfstudio"], "--out"),
        (
            &["--images", images, "--queries", list, "--intrinsics", list],
            "cannot be used with",
        ),
        (
            &["--queries", list, "--images", images, images],
            "takes one directory",
        ),
        (&["--queries", list, "--images", list], "not a directory"),
        (&["--images", images, "--world", "original"], "needs --data"),
    ];
    for (args, want) in cases {
        let o = matloc(&[&base[..], args].concat());
        let t = text(&o);
        assert!(!o.status.success(), "{args:?}: {t}");
        assert!(t.contains(want), "{args:?}: {t}");
        assert!(!t.contains(map), "{args:?} reached the map: {t}");
    }

    let o = matloc(
        &[
            &base[..],
            &["--images", images, "--queries", list, "--format", "hloc"],
        ]
        .concat(),
    );
    let t = text(&o);
    assert!(!o.status.success());
    assert!(t.contains("opening map") && t.contains(map), "{t}");

    let o = matloc(&[
        "localize", "--map", map, "--images", images, "--format", "fisheye",
    ]);
    let t = text(&o);
    assert!(!o.status.success());
    assert!(t.contains("jsonl") && t.contains("tum"), "{t}");
}
