//! The hostile corpus: each case is a directory of generated files and a `matloc` command line.
//! Everything derives from one reduced copy of the `tiny` synthetic world, so the corpus is the
//! same on every run.

use std::ffi::OsString;
use std::fs;
use std::path::{Path, PathBuf};

use crate::fs_tree::copy_tree;

use matloc_core::pose::colmap_from_cam_from_world;
use matloc_data::colmap::{ColmapFormat, read_colmap, write_colmap};
use matloc_data::meganerf::write_mega_nerf;
use matloc_data::read_dataset;
use matloc_pipeline::map::manifest::sha256_hex;
use matloc_synth::{SynthConfig, synthesize};
use serde_json::{Value, json};

/// Frames of the reduced dataset every case starts from (train first, then test).
const FRAMES: usize = 6;

/// One input and the command that reads it.
pub struct Case {
    /// Input family, for the per-category counts.
    pub category: &'static str,
    /// What is broken.
    pub name: String,
    /// The case's own directory.
    pub dir: PathBuf,
    /// Arguments of `matloc`.
    pub args: Vec<OsString>,
    /// Extra environment.
    pub env: Vec<(String, String)>,
    /// The input is impossible: exit 0 is a failure.
    pub must_fail: bool,
    /// Strings a failure's output must contain (file names, fields); `a|b` takes either.
    pub names: Vec<String>,
}

/// Builds every case under `root`.
pub fn build_corpus(root: &Path) -> Vec<Case> {
    let base = Base::new(root);
    let mut g = Gen {
        root: root.to_path_buf(),
        cases: Vec::new(),
    };
    transforms_cases(&mut g, &base);
    colmap_text_cases(&mut g, &base);
    colmap_binary_cases(&mut g, &base);
    image_cases(&mut g, &base);
    decode_cases(&mut g, &base);
    npy_cases(&mut g, &base);
    ply_cases(&mut g, &base);
    meganerf_cases(&mut g, &base);
    map_cases(&mut g);
    built_map_cases(&mut g, &base);
    config_cases(&mut g);
    g.cases
}

/// The reduced `tiny` dataset.
struct Base {
    /// Directory with `images/`, `depth/` and the full `transforms.json`.
    data: PathBuf,
    /// `transforms.json` of the first [`FRAMES`] frames.
    transforms: Value,
    /// Image file names of those frames.
    image_names: Vec<String>,
}

impl Base {
    fn new(root: &Path) -> Base {
        let data = root.join("base");
        synthesize(&SynthConfig::preset("tiny").unwrap(), &data, &|_| {}).unwrap();
        let mut t: Value =
            serde_json::from_slice(&fs::read(data.join("transforms.json")).unwrap()).unwrap();
        let frames: Vec<Value> = t["frames"].as_array().unwrap()[..FRAMES].to_vec();
        let paths: Vec<Value> = frames.iter().map(|f| f["file_path"].clone()).collect();
        t["frames"] = Value::Array(frames);
        t["train_filenames"] = Value::Array(paths[..FRAMES - 2].to_vec());
        t["test_filenames"] = Value::Array(paths[FRAMES - 2..].to_vec());
        t["val_filenames"] = json!([]);
        let image_names = paths
            .iter()
            .map(|p| {
                Path::new(p.as_str().unwrap())
                    .file_name()
                    .unwrap()
                    .to_string_lossy()
                    .into_owned()
            })
            .collect();
        Base {
            data,
            transforms: t,
            image_names,
        }
    }

    /// A dataset directory in `dir`: `transforms` as `transforms.json`, images and depth maps
    /// linked from the base (file by file, so a case can replace one).
    fn dataset(&self, dir: &Path, transforms: &[u8]) {
        fs::create_dir_all(dir.join("images")).unwrap();
        fs::create_dir_all(dir.join("depth")).unwrap();
        for name in &self.image_names {
            let stem = Path::new(name).file_stem().unwrap().to_string_lossy();
            link(
                &self.data.join("images").join(name),
                &dir.join("images").join(name),
            );
            let d = format!("{stem}.npy");
            link(
                &self.data.join("depth").join(&d),
                &dir.join("depth").join(&d),
            );
        }
        fs::write(dir.join("transforms.json"), transforms).unwrap();
    }

    fn transforms_bytes(&self) -> Vec<u8> {
        serde_json::to_vec_pretty(&self.transforms).unwrap()
    }

    fn image(&self, i: usize) -> PathBuf {
        self.data.join("images").join(&self.image_names[i])
    }
}

fn link(from: &Path, to: &Path) {
    let _ = fs::remove_file(to);
    std::os::unix::fs::symlink(from, to).unwrap();
}

struct Gen {
    root: PathBuf,
    cases: Vec<Case>,
}

impl Gen {
    /// A fresh directory for the next case of `category`.
    fn dir(&self, category: &str) -> PathBuf {
        let d = self
            .root
            .join(category)
            .join(format!("{:04}", self.cases.len()));
        fs::create_dir_all(&d).unwrap();
        d
    }

    fn push(
        &mut self,
        category: &'static str,
        name: impl Into<String>,
        dir: PathBuf,
        args: Vec<OsString>,
        must_fail: bool,
        names: Vec<String>,
    ) {
        self.cases.push(Case {
            category,
            name: name.into(),
            dir,
            args,
            env: Vec::new(),
            must_fail,
            names,
        });
    }

    /// `matloc dataset info PATH` (every image and depth map decoded).
    fn info(
        &mut self,
        category: &'static str,
        name: impl Into<String>,
        dir: PathBuf,
        path: &Path,
        must_fail: bool,
        names: &[&str],
    ) {
        let args = vec!["dataset".into(), "info".into(), path.as_os_str().to_owned()];
        self.push(
            category,
            name,
            dir,
            args,
            must_fail,
            names.iter().map(|s| s.to_string()).collect(),
        );
    }
}

/// Cut points spread over `len` bytes (never the full length).
fn cuts(len: usize, n: usize) -> Vec<usize> {
    (0..n).map(|k| k * len / n).collect()
}

/// JSON with `"__RAW__"` replaced by a bare token (NaN, Infinity: not JSON, but written).
fn with_raw(v: &Value, raw: &str) -> Vec<u8> {
    serde_json::to_string_pretty(v)
        .unwrap()
        .replace("\"__RAW__\"", raw)
        .into_bytes()
}

/// Values put into typed fields: (label, value, raw token, is impossible for a number).
fn hostile_values() -> Vec<(&'static str, Value, Option<&'static str>)> {
    vec![
        ("string", json!("abc"), None),
        ("null", Value::Null, None),
        ("negative", json!(-1.0), None),
        ("zero", json!(0), None),
        ("huge", json!(1e300), None),
        ("array", json!([]), None),
        ("object", json!({}), None),
        ("bool", json!(true), None),
        ("tiny", json!(1e-300), None),
        ("2^32", json!(4_294_967_296u64), None),
        ("NaN", json!("__RAW__"), Some("NaN")),
        ("Infinity", json!("__RAW__"), Some("Infinity")),
        ("-Infinity", json!("__RAW__"), Some("-Infinity")),
    ]
}

// ---------------------------------------------------------------------------------------------
// transforms.json

/// Makes what a case's path points at and returns the path as written in the file.
type MakePath = Box<dyn Fn(&Path) -> String>;

fn transforms_cases(g: &mut Gen, base: &Base) {
    const C: &str = "transforms";
    // Every value in every top-level field.
    for field in [
        "fl_x",
        "fl_y",
        "cx",
        "cy",
        "w",
        "h",
        "camera_model",
        "k1",
        "frames",
        "train_filenames",
        "applied_transform",
    ] {
        for (label, value, raw) in hostile_values() {
            let mut t = base.transforms.clone();
            t[field] = value;
            let bytes = with_raw(&t, raw.unwrap_or("\"__RAW__\""));
            let dir = g.dir(C);
            base.dataset(&dir, &bytes);
            let non_finite = raw.is_some();
            let wrong_type = matches!(label, "string" | "array" | "object" | "bool");
            let must = match field {
                "fl_x" | "fl_y" => {
                    non_finite || wrong_type || matches!(label, "negative" | "zero" | "tiny")
                }
                "w" | "h" => label != "null",
                "cx" | "cy" | "k1" => non_finite || wrong_type,
                "camera_model" | "frames" => label != "null",
                _ => (non_finite || wrong_type || label != "null") && label != "array",
            };
            // A value that parses but is implausible is listed as a problem of each frame,
            // under the camera's own name for the field.
            let mut names = vec!["transforms.json|problem(s) found"];
            if must {
                names.push(match field {
                    "fl_x" => "fl_x|`fx`",
                    "fl_y" => "fl_y|`fy`",
                    "w" => "`w`|`width`",
                    "h" => "`h`|`height`",
                    "k1" => "k1|distortion",
                    "frames" => "frames|train_filenames",
                    f => f,
                });
            }
            g.info(
                C,
                format!("{field} = {label}"),
                dir.clone(),
                &dir,
                must,
                &names,
            );
        }
    }
    // Every value in a frame's own fields.
    for field in [
        "file_path",
        "transform_matrix",
        "depth_file_path",
        "fl_x",
        "w",
        "h",
    ] {
        for (label, value, raw) in hostile_values() {
            let mut t = base.transforms.clone();
            t["frames"][0][field] = value;
            let bytes = with_raw(&t, raw.unwrap_or("\"__RAW__\""));
            let dir = g.dir(C);
            base.dataset(&dir, &bytes);
            let must = match field {
                "file_path" | "transform_matrix" => true,
                "depth_file_path" => label != "null",
                _ => label != "null",
            };
            g.info(
                C,
                format!("frames[0].{field} = {label}"),
                dir.clone(),
                &dir,
                must,
                &["transforms.json|frame 0"],
            );
        }
    }
    // Poses that are not rigid motions, or too far to be real.
    let matrices: Vec<(&str, Value)> = vec![
        (
            "scaled rotation",
            json!([[2.0, 0, 0, 0], [0, 2.0, 0, 0], [0, 0, 2.0, 0], [0, 0, 0, 1]]),
        ),
        (
            "all zeros",
            json!([[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0]]),
        ),
        (
            "reflection",
            json!([[-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]),
        ),
        (
            "sheared",
            json!([[1, 0.5, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]),
        ),
        (
            "translation 1e308",
            json!([[1, 0, 0, 1e308], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]),
        ),
        ("3x3", json!([[1, 0, 0], [0, 1, 0], [0, 0, 1]])),
        (
            "ragged",
            json!([[1, 0, 0, 0], [0, 1, 0], [0, 0, 1, 0], [0, 0, 0, 1]]),
        ),
        (
            "bad last row",
            json!([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [5, 5, 5, 5]]),
        ),
    ];
    for (label, m) in matrices {
        let mut t = base.transforms.clone();
        t["frames"][1]["transform_matrix"] = m;
        let dir = g.dir(C);
        base.dataset(&dir, &serde_json::to_vec(&t).unwrap());
        g.info(
            C,
            format!("transform_matrix {label}"),
            dir.clone(),
            &dir,
            true,
            &["transforms.json|frame 1"],
        );
    }
    {
        let mut t = base.transforms.clone();
        t["frames"][1]["transform_matrix"][0][0] = json!("__RAW__");
        let dir = g.dir(C);
        base.dataset(&dir, &with_raw(&t, "NaN"));
        g.info(
            C,
            "transform_matrix with NaN",
            dir.clone(),
            &dir,
            true,
            &["transforms.json|frame 1"],
        );
    }
    // Image sizes no memory holds (the aspect kept, so only the size is wrong).
    for (w, h) in [
        (160_000u64, 120_000u64),
        (4_294_967_295, 3_221_225_471),
        (1 << 40, 3 << 38),
    ] {
        let mut t = base.transforms.clone();
        t["w"] = json!(w);
        t["h"] = json!(h);
        t["fl_x"] = json!(w as f64 * 0.866);
        t["fl_y"] = json!(w as f64 * 0.866);
        t["cx"] = json!(w as f64 / 2.0);
        t["cy"] = json!(h as f64 / 2.0);
        let dir = g.dir(C);
        base.dataset(&dir, &serde_json::to_vec(&t).unwrap());
        g.info(
            C,
            format!("w x h = {w} x {h}"),
            dir.clone(),
            &dir,
            false,
            &["transforms.json|problem(s) found"],
        );
    }
    // Files that are missing, special or elsewhere.
    let specials: Vec<(&str, MakePath)> = vec![
        ("missing image", Box::new(|_| "images/nope.png".into())),
        ("image is a directory", Box::new(|_| "images".into())),
        (
            "image is /dev/zero",
            Box::new(|d| {
                link(Path::new("/dev/zero"), &d.join("images/zero.png"));
                "images/zero.png".into()
            }),
        ),
        (
            "image is /dev/null",
            Box::new(|d| {
                link(Path::new("/dev/null"), &d.join("images/null.png"));
                "images/null.png".into()
            }),
        ),
        (
            "image is a dangling link",
            Box::new(|d| {
                link(&d.join("nowhere"), &d.join("images/dangling.png"));
                "images/dangling.png".into()
            }),
        ),
        (
            "image is a link loop",
            Box::new(|d| {
                link(&d.join("images/loop.png"), &d.join("images/loop.png"));
                "images/loop.png".into()
            }),
        ),
        (
            "image is the transforms file",
            Box::new(|_| "transforms.json".into()),
        ),
        (
            "image path with NUL",
            Box::new(|_| "images/a\u{0}b.png".into()),
        ),
        ("image path empty", Box::new(|_| String::new())),
        (
            "image path very long",
            Box::new(|_| format!("images/{}.png", "a".repeat(5000))),
        ),
    ];
    for (label, make) in specials {
        let dir = g.dir(C);
        base.dataset(&dir, b"{}");
        let p = make(&dir);
        let mut t = base.transforms.clone();
        t["frames"][2]["file_path"] = json!(p);
        fs::write(dir.join("transforms.json"), serde_json::to_vec(&t).unwrap()).unwrap();
        g.info(C, label, dir.clone(), &dir, true, &[]);
    }
    for (label, depth) in [
        ("missing depth", "depth/nope.npy"),
        ("depth is /dev/zero", "depth/zero.npy"),
        ("depth is a directory", "depth"),
    ] {
        let dir = g.dir(C);
        let mut t = base.transforms.clone();
        t["frames"][2]["depth_file_path"] = json!(depth);
        base.dataset(&dir, &serde_json::to_vec(&t).unwrap());
        link(Path::new("/dev/zero"), &dir.join("depth/zero.npy"));
        g.info(C, label, dir.clone(), &dir, true, &[]);
    }
    // The file itself: empty, truncated, not JSON, special.
    let full = base.transforms_bytes();
    for cut in cuts(full.len(), 12) {
        let dir = g.dir(C);
        base.dataset(&dir, &full[..cut]);
        g.info(
            C,
            format!("truncated at {cut}"),
            dir.clone(),
            &dir,
            true,
            &["transforms.json"],
        );
    }
    let odd: Vec<(&str, Vec<u8>)> = vec![
        ("nested 100000 deep", "[".repeat(100_000).into_bytes()),
        ("top-level array", b"[1, 2, 3]".to_vec()),
        ("top-level string", b"\"frames\"".to_vec()),
        ("UTF-16", {
            let mut v = vec![0xff, 0xfe];
            for u in String::from_utf8_lossy(&full).encode_utf16() {
                v.extend_from_slice(&u.to_le_bytes());
            }
            v
        }),
        ("invalid UTF-8", {
            let mut v = full.clone();
            v.insert(20, 0xff);
            v
        }),
        ("duplicate frames key", {
            let s = String::from_utf8_lossy(&full).into_owned();
            s.replacen("\"frames\"", "\"frames\": [], \"frames\"", 1)
                .into_bytes()
        }),
        (
            "binary garbage",
            (0..4096u32)
                .map(|i| (i.wrapping_mul(2_654_435_761) >> 13) as u8)
                .collect(),
        ),
    ];
    for (label, bytes) in odd {
        let dir = g.dir(C);
        base.dataset(&dir, &bytes);
        g.info(
            C,
            label,
            dir.clone(),
            &dir,
            label != "duplicate frames key",
            &["transforms.json"],
        );
    }
    {
        let dir = g.dir(C);
        base.dataset(&dir, b"");
        fs::remove_file(dir.join("transforms.json")).unwrap();
        link(Path::new("/dev/zero"), &dir.join("transforms.json"));
        g.info(
            C,
            "transforms.json is /dev/zero",
            dir.clone(),
            &dir,
            true,
            &[],
        );
        let dir2 = g.dir(C);
        g.info(
            C,
            "transforms.json named directly but /dev/zero",
            dir2,
            &dir.join("transforms.json"),
            true,
            &[],
        );
    }
}

// ---------------------------------------------------------------------------------------------
// COLMAP

/// A COLMAP text model of the base frames: `(cameras.txt, images.txt, points3D.txt)`.
fn colmap_text(base: &Base) -> (String, String, String) {
    let ds = read_dataset(&base.data).unwrap();
    let c = &ds.frames[0].camera;
    let cameras = format!(
        "# Camera list\n1 PINHOLE {} {} {} {} {} {}\n",
        c.width, c.height, c.fx, c.fy, c.cx, c.cy
    );
    let mut images = String::from("# Image list\n");
    for (i, f) in ds.frames.iter().take(FRAMES).enumerate() {
        let (q, t) = colmap_from_cam_from_world(&f.cam_from_world);
        let name = f.image_path.file_name().unwrap().to_string_lossy();
        images.push_str(&format!(
            "{} {} {} {} {} {} {} {} 1 {name}\n",
            i + 1,
            q[0],
            q[1],
            q[2],
            q[3],
            t[0],
            t[1],
            t[2]
        ));
        images.push_str(&format!("10 20 {}\n", i + 1));
    }
    let mut points = String::from("# 3D point list\n");
    for i in 0..FRAMES {
        points.push_str(&format!(
            "{} {} {} 0 128 128 128 0.5 {} 0\n",
            i + 1,
            i as f64,
            -(i as f64),
            i + 1
        ));
    }
    (cameras, images, points)
}

/// A COLMAP dataset directory: `sparse/0/` with the given files, `images/` linked.
fn colmap_dir(g: &Gen, base: &Base, category: &str, files: &[(&str, &[u8])]) -> PathBuf {
    let dir = g.dir(category);
    let model = dir.join("sparse/0");
    fs::create_dir_all(&model).unwrap();
    fs::create_dir_all(dir.join("images")).unwrap();
    for i in 0..FRAMES {
        link(
            &base.image(i),
            &dir.join("images").join(&base.image_names[i]),
        );
    }
    for (name, bytes) in files {
        fs::write(model.join(name), bytes).unwrap();
    }
    dir
}

fn colmap_text_cases(g: &mut Gen, base: &Base) {
    const C: &str = "colmap-text";
    let (cams, imgs, pts) = colmap_text(base);
    let run = |g: &mut Gen,
               label: String,
               cams: &str,
               imgs: &str,
               pts: &str,
               must: bool,
               names: &[&str]| {
        let dir = colmap_dir(
            g,
            base,
            C,
            &[
                ("cameras.txt", cams.as_bytes()),
                ("images.txt", imgs.as_bytes()),
                ("points3D.txt", pts.as_bytes()),
            ],
        );
        g.info(C, label, dir.clone(), &dir, must, names);
    };
    run(g, "valid model".into(), &cams, &imgs, &pts, false, &[]);
    let c = read_dataset(&base.data).unwrap().frames[0].camera;
    let camera_lines: Vec<(&str, String)> = vec![
        ("unknown model", "1 NOT_A_MODEL 160 120 1 2 3".into()),
        (
            "fisheye model",
            format!("1 OPENCV_FISHEYE 160 120 {} {} 80 60 0 0 0 0", c.fx, c.fy),
        ),
        (
            "thin prism model",
            "1 THIN_PRISM_FISHEYE 160 120 1 1 1 1 0 0 0 0 0 0 0 0".into(),
        ),
        ("too few params", "1 PINHOLE 160 120 100 100".into()),
        (
            "too many params",
            "1 PINHOLE 160 120 100 100 80 60 1 2".into(),
        ),
        (
            "zero width",
            format!("1 PINHOLE 0 120 {} {} 80 60", c.fx, c.fy),
        ),
        (
            "negative height",
            format!("1 PINHOLE 160 -120 {} {} 80 60", c.fx, c.fy),
        ),
        (
            "width 2^32",
            format!("1 PINHOLE 4294967296 120 {} {} 80 60", c.fx, c.fy),
        ),
        (
            "width text",
            format!("1 PINHOLE wide 120 {} {} 80 60", c.fx, c.fy),
        ),
        ("NaN focal", "1 PINHOLE 160 120 nan nan 80 60".into()),
        ("inf focal", "1 PINHOLE 160 120 inf inf 80 60".into()),
        ("zero focal", "1 PINHOLE 160 120 0 0 80 60".into()),
        ("negative focal", "1 PINHOLE 160 120 -100 -100 80 60".into()),
        (
            "NaN principal point",
            format!("1 PINHOLE 160 120 {} {} nan 60", c.fx, c.fy),
        ),
        (
            "huge distortion",
            format!("1 OPENCV 160 120 {} {} 80 60 1e30 0 0 0", c.fx, c.fy),
        ),
        (
            "camera id 0",
            format!("0 PINHOLE 160 120 {} {} 80 60", c.fx, c.fy),
        ),
        (
            "camera id text",
            format!("x PINHOLE 160 120 {} {} 80 60", c.fx, c.fy),
        ),
        ("only an id", "1".into()),
        (
            "huge image for memory",
            format!(
                "1 PINHOLE 4000000000 3000000000 {} {} 2e9 1.5e9",
                3.4e9, 3.4e9
            ),
        ),
    ];
    for (label, line) in camera_lines {
        let must = !label.starts_with("huge image");
        run(
            g,
            format!("cameras.txt {label}"),
            &format!("{line}\n"),
            &imgs,
            &pts,
            must,
            &["cameras.txt|images.txt|problem(s) found"],
        );
    }
    // images.txt: edit the first image's line.
    let first: Vec<&str> = imgs.lines().nth(1).unwrap().split(' ').collect();
    let edit = |k: usize, v: &str| -> String {
        let mut f = first.clone();
        f[k] = v;
        let line = f.join(" ");
        let mut out: Vec<String> = imgs.lines().map(str::to_string).collect();
        out[1] = line;
        out.join("\n") + "\n"
    };
    let image_edits: Vec<(&str, String, bool)> = vec![
        ("NaN quaternion", edit(1, "nan"), true),
        (
            "zero quaternion",
            {
                let mut f = first.clone();
                for k in 1..5 {
                    f[k] = "0";
                }
                let mut out: Vec<String> = imgs.lines().map(str::to_string).collect();
                out[1] = f.join(" ");
                out.join("\n") + "\n"
            },
            true,
        ),
        ("inf translation", edit(5, "inf"), true),
        ("translation 1e308", edit(6, "1e308"), true),
        ("camera id missing from cameras.txt", edit(8, "99"), true),
        ("image file missing", edit(9, "nope.png"), true),
        (
            "image name escapes",
            edit(9, "../../../../etc/passwd"),
            true,
        ),
        ("image id text", edit(0, "first"), true),
        ("short line", "# x\n1 1 0 0\n".into(), true),
        (
            "duplicate image id",
            {
                let mut out: Vec<String> = imgs.lines().map(str::to_string).collect();
                let dup = out[1].clone();
                out[3] = dup.replacen(&first[9].to_string(), &base.image_names[1], 1);
                out.join("\n") + "\n"
            },
            false,
        ),
        (
            "odd point2D triplet",
            {
                let mut out: Vec<String> = imgs.lines().map(str::to_string).collect();
                out[2] = "10 20".into();
                out.join("\n") + "\n"
            },
            true,
        ),
        (
            "NaN point2D",
            {
                let mut out: Vec<String> = imgs.lines().map(str::to_string).collect();
                out[2] = "nan nan 1".into();
                out.join("\n") + "\n"
            },
            false,
        ),
        (
            "point2D refers to a missing 3D point",
            {
                let mut out: Vec<String> = imgs.lines().map(str::to_string).collect();
                out[2] = "10 20 999999".into();
                out.join("\n") + "\n"
            },
            false,
        ),
        (
            "missing points line",
            {
                let mut out: Vec<String> = imgs.lines().map(str::to_string).collect();
                out.remove(2);
                out.join("\n") + "\n"
            },
            false,
        ),
        ("no images", "# nothing\n".into(), true),
    ];
    for (label, text, must) in image_edits {
        run(
            g,
            format!("images.txt {label}"),
            &cams,
            &text,
            &pts,
            must,
            &["images.txt|points3D.txt|problem(s) found"],
        );
    }
    let first_point: Vec<&str> = pts.lines().nth(1).unwrap().split(' ').collect();
    let pedit = |k: usize, v: &str| -> String {
        let mut f = first_point.clone();
        f[k] = v;
        let mut out: Vec<String> = pts.lines().map(str::to_string).collect();
        out[1] = f.join(" ");
        out.join("\n") + "\n"
    };
    let point_edits: Vec<(&str, String, bool)> = vec![
        ("NaN x", pedit(1, "nan"), true),
        ("inf z", pedit(3, "inf"), true),
        ("colour 300", pedit(4, "300"), true),
        ("track to a missing image", pedit(8, "77"), false),
        (
            "odd track",
            {
                let mut out: Vec<String> = pts.lines().map(str::to_string).collect();
                out[1] = format!("{} 5", out[1]);
                out.join("\n") + "\n"
            },
            true,
        ),
        ("negative error", pedit(7, "-1"), false),
        ("id text", pedit(0, "p"), true),
        ("id 2^64", pedit(0, "18446744073709551616"), true),
    ];
    for (label, text, must) in point_edits {
        run(
            g,
            format!("points3D.txt {label}"),
            &cams,
            &imgs,
            &text,
            must,
            &["points3D.txt"],
        );
    }
    for (file, text) in [
        ("cameras.txt", &cams),
        ("images.txt", &imgs),
        ("points3D.txt", &pts),
    ] {
        for cut in cuts(text.len(), 5).into_iter().skip(1) {
            let t = &text[..cut];
            let (c2, i2, p2) = match file {
                "cameras.txt" => (t, imgs.as_str(), pts.as_str()),
                "images.txt" => (cams.as_str(), t, pts.as_str()),
                _ => (cams.as_str(), imgs.as_str(), t),
            };
            run(
                g,
                format!("{file} truncated at {cut}"),
                c2,
                i2,
                p2,
                false,
                &[],
            );
        }
    }
    // A model with a file missing.
    for missing in ["cameras.txt", "images.txt", "points3D.txt"] {
        let files: Vec<(&str, &[u8])> = [
            ("cameras.txt", cams.as_bytes()),
            ("images.txt", imgs.as_bytes()),
            ("points3D.txt", pts.as_bytes()),
        ]
        .into_iter()
        .filter(|(n, _)| *n != missing)
        .collect();
        let dir = colmap_dir(g, base, C, &files);
        g.info(
            C,
            format!("{missing} missing"),
            dir.clone(),
            &dir,
            missing != "points3D.txt",
            &[],
        );
    }
}

fn colmap_binary_cases(g: &mut Gen, base: &Base) {
    const C: &str = "colmap-binary";
    let (cams, imgs, pts) = colmap_text(base);
    let text_dir = g.root.join("colmap-binary-source");
    fs::create_dir_all(&text_dir).unwrap();
    fs::write(text_dir.join("cameras.txt"), &cams).unwrap();
    fs::write(text_dir.join("images.txt"), &imgs).unwrap();
    fs::write(text_dir.join("points3D.txt"), &pts).unwrap();
    let model = read_colmap(&text_dir).unwrap();
    let bin_dir = g.root.join("colmap-binary-source/bin");
    write_colmap(&model, &bin_dir, ColmapFormat::Binary).unwrap();
    let files: Vec<(&str, Vec<u8>)> = ["cameras.bin", "images.bin", "points3D.bin"]
        .into_iter()
        .map(|n| (n, fs::read(bin_dir.join(n)).unwrap()))
        .collect();
    let run = |g: &mut Gen, label: String, which: usize, bytes: Vec<u8>, must: bool| {
        let mut set: Vec<(&str, &[u8])> = files.iter().map(|(n, b)| (*n, b.as_slice())).collect();
        set[which].1 = &bytes;
        let dir = colmap_dir(g, base, C, &set);
        let name = files[which].0;
        let names = format!("{name}|problem(s) found");
        g.info(
            C,
            format!("{name} {label}"),
            dir.clone(),
            &dir,
            must,
            &[names.as_str()],
        );
    };
    run(g, "valid".into(), 0, files[0].1.clone(), false);
    // The first point's x (after the count and its id) not a number.
    let mut nan = files[2].1.clone();
    nan[16..24].copy_from_slice(&f64::NAN.to_le_bytes());
    run(g, "NaN x".into(), 2, nan, true);
    for (which, (name, bytes)) in files.iter().enumerate() {
        for cut in cuts(bytes.len(), 8).into_iter().skip(1) {
            let must = *name != "points3D.bin";
            run(
                g,
                format!("truncated at {cut}"),
                which,
                bytes[..cut].to_vec(),
                must,
            );
        }
        // A count claiming more records than any file holds.
        for count in [u64::MAX, 1 << 40, 1_000_000] {
            let mut b = bytes.clone();
            b[..8].copy_from_slice(&count.to_le_bytes());
            run(
                g,
                format!("count {count}"),
                which,
                b,
                *name != "points3D.bin",
            );
        }
        // Bytes overwritten with 0xff runs at spread positions.
        for at in cuts(bytes.len(), 5).into_iter().skip(1) {
            let mut b = bytes.clone();
            for k in at..(at + 8).min(b.len()) {
                b[k] = 0xff;
            }
            run(g, format!("0xff at {at}"), which, b, false);
        }
        let mut longer = bytes.clone();
        longer.extend_from_slice(&[0u8; 13]);
        run(g, "trailing bytes".into(), which, longer, false);
    }
    // cameras.bin: count u64, then id u32, model i32, width u64, height u64, params f64…
    let cam = &files[0].1;
    let set_at = |at: usize, v: &[u8]| {
        let mut b = cam.clone();
        b[at..at + v.len()].copy_from_slice(v);
        b
    };
    for (label, b) in [
        ("model 99", set_at(12, &99i32.to_le_bytes())),
        ("model -1", set_at(12, &(-1i32).to_le_bytes())),
        ("fisheye model", set_at(12, &5i32.to_le_bytes())),
        ("width 0", set_at(16, &0u64.to_le_bytes())),
        ("width 2^40", set_at(16, &(1u64 << 40).to_le_bytes())),
        ("NaN focal", set_at(32, &f64::NAN.to_le_bytes())),
        ("inf cy", set_at(56, &f64::INFINITY.to_le_bytes())),
        ("negative focal", set_at(32, &(-5.0f64).to_le_bytes())),
    ] {
        run(g, label.into(), 0, b, true);
    }
    // images.bin: count u64, id u32, q 4×f64, t 3×f64, camera id u32, name, NUL, n u64, …
    let img = &files[1].1;
    let set_img = |at: usize, v: &[u8]| {
        let mut b = img.clone();
        b[at..at + v.len()].copy_from_slice(v);
        b
    };
    for (label, b, must) in [
        ("NaN qw", set_img(12, &f64::NAN.to_le_bytes()), true),
        (
            "zero quaternion",
            {
                let mut b = img.clone();
                b[12..44].fill(0);
                b
            },
            true,
        ),
        ("inf tx", set_img(44, &f64::INFINITY.to_le_bytes()), true),
        ("camera 77", set_img(68, &77u32.to_le_bytes()), true),
        (
            "name without NUL",
            {
                let mut b = img.clone();
                let nul = b[72..].iter().position(|&c| c == 0).unwrap() + 72;
                b.truncate(nul);
                b
            },
            true,
        ),
        (
            "points2D count huge",
            {
                let mut b = img.clone();
                let nul = b[72..].iter().position(|&c| c == 0).unwrap() + 72;
                b[nul + 1..nul + 9].copy_from_slice(&(u64::MAX / 2).to_le_bytes());
                b
            },
            true,
        ),
    ] {
        run(g, label.into(), 1, b, must);
    }
}

// ---------------------------------------------------------------------------------------------
// Images

fn crc32(bytes: &[u8]) -> u32 {
    let mut c = !0u32;
    for &b in bytes {
        c ^= u32::from(b);
        for _ in 0..8 {
            c = if c & 1 != 0 {
                0xEDB8_8320 ^ (c >> 1)
            } else {
                c >> 1
            };
        }
    }
    !c
}

fn png_chunk(out: &mut Vec<u8>, kind: &[u8; 4], data: &[u8]) {
    out.extend_from_slice(&(data.len() as u32).to_be_bytes());
    let mut c = kind.to_vec();
    c.extend_from_slice(data);
    out.extend_from_slice(&c);
    out.extend_from_slice(&crc32(&c).to_be_bytes());
}

/// zlib stream of stored (uncompressed) deflate blocks.
fn zlib_stored(data: &[u8]) -> Vec<u8> {
    let mut out = vec![0x78, 0x01];
    let chunks: Vec<&[u8]> = if data.is_empty() {
        vec![&[]]
    } else {
        data.chunks(65_535).collect()
    };
    for (i, c) in chunks.iter().enumerate() {
        out.push(u8::from(i + 1 == chunks.len()));
        out.extend_from_slice(&(c.len() as u16).to_le_bytes());
        out.extend_from_slice(&(!(c.len() as u16)).to_le_bytes());
        out.extend_from_slice(c);
    }
    let (mut a, mut b) = (1u32, 0u32);
    for &x in data {
        a = (a + u32::from(x)) % 65_521;
        b = (b + a) % 65_521;
    }
    out.extend_from_slice(&((b << 16) | a).to_be_bytes());
    out
}

/// A PNG of `w × h` pixels with `colour` type and 8-bit samples; `idat: None` fills grey rows.
fn png(w: u32, h: u32, colour: u8, bit_depth: u8, idat: Option<Vec<u8>>) -> Vec<u8> {
    let mut out = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut ihdr = Vec::new();
    ihdr.extend_from_slice(&w.to_be_bytes());
    ihdr.extend_from_slice(&h.to_be_bytes());
    ihdr.extend_from_slice(&[bit_depth, colour, 0, 0, 0]);
    png_chunk(&mut out, b"IHDR", &ihdr);
    let channels = match colour {
        0 => 1,
        2 => 3,
        4 => 2,
        6 => 4,
        _ => 1,
    };
    let data = idat.unwrap_or_else(|| {
        let row = 1 + w as usize * channels * usize::from(bit_depth.max(8) / 8);
        let mut raw = vec![0x80u8; row * h as usize];
        for r in 0..h as usize {
            raw[r * row] = 0;
        }
        zlib_stored(&raw)
    });
    png_chunk(&mut out, b"IDAT", &data);
    png_chunk(&mut out, b"IEND", &[]);
    out
}

fn image_cases(g: &mut Gen, base: &Base) {
    const C: &str = "images";
    let target = &base.image_names[1];
    let good = fs::read(base.image(1)).unwrap();
    let put = |g: &mut Gen,
               label: String,
               bytes: Option<Vec<u8>>,
               must: bool,
               env: Option<(&str, &str)>| {
        let dir = g.dir(C);
        base.dataset(&dir, &base.transforms_bytes());
        let p = dir.join("images").join(target);
        fs::remove_file(&p).unwrap();
        match bytes {
            Some(b) => fs::write(&p, b).unwrap(),
            None => link(Path::new("/dev/zero"), &p),
        }
        g.info(C, label, dir.clone(), &dir, must, &[target.as_str()]);
        if let Some((k, v)) = env {
            g.cases.last_mut().unwrap().env.push((k.into(), v.into()));
        }
    };
    for cut in cuts(good.len(), 10) {
        put(
            g,
            format!("PNG truncated at {cut}"),
            Some(good[..cut].to_vec()),
            true,
            None,
        );
    }
    // The IDAT of the real image corrupted at spread offsets (zlib or filter bytes).
    let idat_at = good.windows(4).position(|w| w == b"IDAT").unwrap() + 4;
    for k in 0..8 {
        let mut b = good.clone();
        let at = idat_at + 2 + k * (good.len() - idat_at - 20) / 8;
        for x in &mut b[at..at + 4] {
            *x ^= 0x5a;
        }
        put(
            g,
            format!("PNG IDAT corrupted at {at}"),
            Some(b),
            false,
            None,
        );
    }
    let ihdr_crc = {
        let mut b = good.clone();
        b[29] ^= 1;
        b
    };
    put(
        g,
        "PNG IHDR checksum wrong".into(),
        Some(ihdr_crc),
        false,
        None,
    );
    put(
        g,
        "bad zlib header".into(),
        Some(png(160, 120, 2, 8, Some(vec![0xff, 0xff, 1, 2, 3]))),
        true,
        None,
    );
    put(
        g,
        "zlib stream too short".into(),
        Some(png(160, 120, 2, 8, Some(zlib_stored(&[0; 100])))),
        true,
        None,
    );
    put(
        g,
        "wrong size 100x100".into(),
        Some(png(100, 100, 2, 8, None)),
        true,
        None,
    );
    put(g, "1x1".into(), Some(png(1, 1, 2, 8, None)), true, None);
    put(g, "0x0".into(), Some(png(0, 0, 2, 8, None)), true, None);
    put(g, "0x120".into(), Some(png(0, 120, 2, 8, None)), true, None);
    put(
        g,
        "header 100000x75000".into(),
        Some(png(100_000, 75_000, 2, 8, Some(zlib_stored(&[0; 64])))),
        true,
        None,
    );
    put(
        g,
        "header 2^31-1 square".into(),
        Some(png(0x7fff_ffff, 0x7fff_ffff, 2, 8, Some(vec![]))),
        true,
        None,
    );
    put(
        g,
        "header 2^32-1 square".into(),
        Some(png(u32::MAX, u32::MAX, 2, 8, Some(vec![]))),
        true,
        None,
    );
    put(
        g,
        "grey 8-bit".into(),
        Some(png(160, 120, 0, 8, None)),
        false,
        None,
    );
    put(
        g,
        "RGBA".into(),
        Some(png(160, 120, 6, 8, None)),
        false,
        None,
    );
    put(
        g,
        "RGB 16-bit".into(),
        Some(png(160, 120, 2, 16, None)),
        false,
        None,
    );
    put(
        g,
        "bit depth 3".into(),
        Some(png(160, 120, 2, 3, None)),
        true,
        None,
    );
    put(
        g,
        "colour type 7".into(),
        Some(png(160, 120, 7, 8, None)),
        true,
        None,
    );
    put(
        g,
        "palette without PLTE".into(),
        Some(png(160, 120, 3, 8, None)),
        true,
        None,
    );
    put(g, "empty file".into(), Some(Vec::new()), true, None);
    put(
        g,
        "text file".into(),
        Some(b"not an image at all\n".to_vec()),
        true,
        None,
    );
    put(g, "/dev/zero".into(), None, true, None);
    put(
        g,
        "GIF magic".into(),
        Some(b"GIF89a\x10\x00\x10\x00\x00\x00\x00".to_vec()),
        true,
        None,
    );
    put(
        g,
        "BMP magic".into(),
        Some(b"BM\x00\x00\x00\x00\x00\x00\x00\x00\x36\x00\x00\x00".to_vec()),
        true,
        None,
    );
    // JPEG: markers only, a frame header claiming 65535², truncated segments.
    let soi = vec![0xff, 0xd8];
    let sof = |w: u16, h: u16| {
        let mut v = soi.clone();
        v.extend_from_slice(&[0xff, 0xc0, 0, 17, 8]);
        v.extend_from_slice(&h.to_be_bytes());
        v.extend_from_slice(&w.to_be_bytes());
        v.extend_from_slice(&[3, 1, 0x11, 0, 2, 0x11, 1, 3, 0x11, 1]);
        v
    };
    put(g, "JPEG SOI only".into(), Some(soi.clone()), true, None);
    put(
        g,
        "JPEG SOF 65535x65535 no data".into(),
        Some(sof(65_535, 65_535)),
        true,
        None,
    );
    put(
        g,
        "JPEG SOF 160x120 no data".into(),
        Some(sof(160, 120)),
        true,
        None,
    );
    put(g, "JPEG SOF 0x0".into(), Some(sof(0, 0)), true, None);
    let mut seg = soi.clone();
    seg.extend_from_slice(&[0xff, 0xe0, 0xff, 0xff, 1, 2, 3]);
    put(
        g,
        "JPEG segment longer than the file".into(),
        Some(seg),
        true,
        None,
    );
    let mut eoi = sof(160, 120);
    eoi.extend_from_slice(&[0xff, 0xd9]);
    put(g, "JPEG SOF then EOI".into(), Some(eoi), true, None);
    // A real image past the memory budget: refused with a memory-limit error.
    put(
        g,
        "2000x1500 PNG under MATLOC_MEMORY_LIMIT=32M".into(),
        Some(png(2000, 1500, 2, 8, None)),
        true,
        Some(("MATLOC_MEMORY_LIMIT", "32M")),
    );
    g.cases
        .last_mut()
        .unwrap()
        .names
        .push("MATLOC_MEMORY_LIMIT".into());
    put(
        g,
        "MATLOC_MEMORY_LIMIT not a size".into(),
        Some(png(2000, 1500, 2, 8, None)),
        true,
        Some(("MATLOC_MEMORY_LIMIT", "lots")),
    );
    g.cases.last_mut().unwrap().names = vec!["MATLOC_MEMORY_LIMIT".into()];
}

// ---------------------------------------------------------------------------------------------
// Images and depth maps whose header is sound and whose data is not: `dataset info` decodes
// them, and `map build` refuses them before it writes anything.

/// The cheapest map build that completes on the `tiny` world (seconds): a few NeRF steps on a
/// small hash table, a few encoder steps, one place epoch, no rendered place views.
const CHEAP_MAP_CONFIG: &str = r#"{
  "nerf": {"steps": 80, "checkpoint_every": 80,
    "model_overrides": {"field": {"log2_table_size": 12, "max_resolution": 128},
      "train": {"batch_rays": 256, "march": {"steps": 64, "max_samples": 16},
                "occupancy_warmup_steps": 8},
      "render": {"march": {"steps": 64}}}},
  "structure": {"triangulate": {"max_keypoints": 300}},
  "encoder": {"train": {"steps": 5, "head_phase": {"steps": 0}}},
  "place": {"rendered": {"per_view": 0}, "train": {"epochs": 1}},
  "calibration": {"max_views": 2}
}"#;

/// A JPEG of the repository's fixtures (320×240, the aspect of the `tiny` world's 160×120).
fn fixture_jpeg() -> Vec<u8> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("fixtures/outside-smoke/survey/images/survey_00001.jpg");
    fs::read(p).unwrap()
}

fn decode_cases(g: &mut Gen, base: &Base) {
    const C: &str = "decode";
    let stem = Path::new(&base.image_names[1])
        .file_stem()
        .unwrap()
        .to_string_lossy()
        .into_owned();
    // Frame 1's image (or depth map, `depth`) replaced by `bytes` under `file` (a path
    // relative to the dataset), then `dataset info` and, with `build`, `map build`.
    let put = |g: &mut Gen,
               label: &str,
               file: String,
               depth: bool,
               bytes: Vec<u8>,
               must: bool,
               build: bool| {
        for build in [false, true].into_iter().filter(|&b| !b || build) {
            let dir = g.dir(C);
            let mut t = base.transforms.clone();
            let key = if depth {
                "depth_file_path"
            } else {
                "file_path"
            };
            let old = t["frames"][1][key].as_str().unwrap().to_string();
            t["frames"][1][key] = json!(file);
            if !depth {
                for list in ["train_filenames", "test_filenames"] {
                    for v in t[list].as_array_mut().unwrap() {
                        if v.as_str() == Some(old.as_str()) {
                            *v = json!(file);
                        }
                    }
                }
            }
            base.dataset(&dir, &serde_json::to_vec_pretty(&t).unwrap());
            let _ = fs::remove_file(dir.join(&old));
            fs::write(dir.join(&file), &bytes).unwrap();
            let name = Path::new(&file)
                .file_name()
                .unwrap()
                .to_string_lossy()
                .into_owned();
            if build {
                let config = dir.join("config.json");
                fs::write(&config, CHEAP_MAP_CONFIG).unwrap();
                let args: Vec<OsString> = vec![
                    "map".into(),
                    "build".into(),
                    "--quiet".into(),
                    "--data".into(),
                    dir.clone().into_os_string(),
                    "--out".into(),
                    dir.join("map").into_os_string(),
                    "--config".into(),
                    config.into_os_string(),
                ];
                g.push(
                    C,
                    format!("map build: {label}"),
                    dir,
                    args,
                    must,
                    vec![name],
                );
            } else {
                g.info(
                    C,
                    format!("dataset info: {label}"),
                    dir.clone(),
                    &dir,
                    must,
                    &[&name],
                );
            }
        }
    };
    let png_name = format!("images/{stem}.png");
    let good = fs::read(base.image(1)).unwrap();
    put(
        g,
        "PNG truncated at half",
        png_name.clone(),
        false,
        good[..good.len() / 2].to_vec(),
        true,
        true,
    );
    put(
        g,
        "IDAT that is not zlib",
        png_name.clone(),
        false,
        png(160, 120, 2, 8, Some((0..200u8).collect())),
        true,
        true,
    );
    put(
        g,
        "IHDR 64000x48000 with a tiny IDAT",
        png_name,
        false,
        png(64_000, 48_000, 2, 8, Some(zlib_stored(&[0; 64]))),
        true,
        true,
    );
    let jpeg = fixture_jpeg();
    let jpg_name = format!("images/{stem}.jpg");
    put(
        g,
        "JPEG (control)",
        jpg_name.clone(),
        false,
        jpeg.clone(),
        false,
        false,
    );
    put(
        g,
        "JPEG truncated at 60 %",
        jpg_name,
        false,
        jpeg[..jpeg.len() * 6 / 10].to_vec(),
        true,
        true,
    );
    let depth_name = format!("depth/{stem}.png");
    put(
        g,
        "8-bit PNG as a depth map",
        depth_name.clone(),
        true,
        png(160, 120, 0, 8, None),
        true,
        true,
    );
    for case in g.cases.iter_mut().rev().take(2) {
        case.names.push("16-bit".into());
    }
    put(
        g,
        "RGB 16-bit PNG as a depth map",
        depth_name.clone(),
        true,
        png(160, 120, 2, 16, None),
        true,
        false,
    );
    put(
        g,
        "16-bit grey PNG depth map (control)",
        depth_name,
        true,
        png(160, 120, 0, 16, None),
        false,
        false,
    );
}

// ---------------------------------------------------------------------------------------------
// .npy depth maps

fn npy(descr: &str, fortran: bool, shape: &str, data: &[u8]) -> Vec<u8> {
    matloc_data::images::npy_with_header(
        &format!(
            "{{'descr': '{descr}', 'fortran_order': {}, 'shape': {shape}, }}",
            if fortran { "True" } else { "False" }
        ),
        1,
        data,
    )
}

fn npy_cases(g: &mut Gen, base: &Base) {
    const C: &str = "npy";
    let stem = Path::new(&base.image_names[1])
        .file_stem()
        .unwrap()
        .to_string_lossy()
        .into_owned();
    let target = format!("{stem}.npy");
    let (w, h) = (160usize, 120usize);
    let n = w * h;
    let put = |g: &mut Gen, label: String, bytes: Vec<u8>, must: bool| {
        let dir = g.dir(C);
        base.dataset(&dir, &base.transforms_bytes());
        let p = dir.join("depth").join(&target);
        fs::remove_file(&p).unwrap();
        fs::write(&p, bytes).unwrap();
        g.info(C, label, dir.clone(), &dir, must, &[target.as_str()]);
    };
    let shape = format!("({h}, {w})");
    // Every dtype numpy writes, little- and big-endian.
    for (descr, size) in [
        ("<f2", 2),
        ("<f4", 4),
        ("<f8", 8),
        (">f4", 4),
        (">f8", 8),
        ("=f4", 4),
        ("f4", 4),
        ("<i1", 1),
        ("<i2", 2),
        ("<i4", 4),
        ("<i8", 8),
        (">i4", 4),
        ("|u1", 1),
        ("<u2", 2),
        ("<u4", 4),
        ("<u8", 8),
        ("|b1", 1),
        ("<c8", 8),
        ("<c16", 16),
        ("|O", 8),
        ("<U4", 16),
        ("|S4", 4),
        ("|V4", 4),
        ("<M8[s]", 8),
        ("<m8[s]", 8),
        ("<f16", 16),
        ("zz", 4),
    ] {
        let value: Vec<u8> = match descr {
            "<f4" | "=f4" | "f4" => 10.0f32.to_le_bytes().to_vec(),
            "<f8" => 10.0f64.to_le_bytes().to_vec(),
            _ => vec![1; size],
        };
        let data: Vec<u8> = value.iter().copied().cycle().take(n * size).collect();
        let ok = matches!(descr, "<f4" | "<f8" | "=f4" | "f4");
        put(
            g,
            format!("dtype {descr}"),
            npy(descr, false, &shape, &data),
            !ok,
        );
    }
    let f4 = |v: f32| -> Vec<u8> {
        v.to_le_bytes()
            .iter()
            .copied()
            .cycle()
            .take(4 * n)
            .collect()
    };
    for (label, sh, must) in [
        ("shape ()", "()".to_string(), true),
        ("shape (N,)", format!("({n},)"), true),
        ("shape (H, W, 3)", format!("({h}, {w}, 3)"), true),
        ("shape (H, W, 1)", format!("({h}, {w}, 1)"), false),
        ("shape (W, H)", format!("({w}, {h})"), true),
        ("shape (0, 0)", "(0, 0)".into(), true),
        (
            "shape (1e12, 1e12)",
            "(1000000000000, 1000000000000)".into(),
            true,
        ),
        ("shape (2^63, 2)", "(9223372036854775808, 2)".into(), true),
        ("shape (-1, W)", format!("(-1, {w})"), true),
        ("shape text", "('a', 'b')".into(), true),
    ] {
        put(g, label.into(), npy("<f4", false, &sh, &f4(5.0)), must);
    }
    for (label, v) in [
        ("all NaN", f32::NAN),
        ("all inf", f32::INFINITY),
        ("all negative", -3.0),
        ("all zero", 0.0),
        ("all 1e30", 1e30),
    ] {
        // A depth map with no usable value is not a surface.
        put(g, label.into(), npy("<f4", false, &shape, &f4(v)), false);
    }
    put(
        g,
        "fortran order".into(),
        npy("<f4", true, &shape, &f4(5.0)),
        false,
    );
    let good = npy("<f4", false, &shape, &f4(5.0));
    for cut in cuts(good.len(), 8) {
        put(g, format!("truncated at {cut}"), good[..cut].to_vec(), true);
    }
    let mut longer = good.clone();
    longer.extend_from_slice(&[0; 4]);
    put(g, "one value too many".into(), longer, true);
    put(
        g,
        "bad magic".into(),
        {
            let mut b = good.clone();
            b[1] = b'X';
            b
        },
        true,
    );
    put(
        g,
        "version 2".into(),
        matloc_data::images::npy_with_header(
            &format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {shape}, }}"),
            2,
            &f4(5.0),
        ),
        false,
    );
    put(
        g,
        "version 9".into(),
        {
            let mut b = good.clone();
            b[6] = 9;
            b
        },
        true,
    );
    put(
        g,
        "header length past the end".into(),
        {
            let mut b = good[..20].to_vec();
            b[8..10].copy_from_slice(&u16::MAX.to_le_bytes());
            b
        },
        true,
    );
    put(
        g,
        "header not a dict".into(),
        matloc_data::images::npy_with_header("[1, 2, 3]", 1, &f4(5.0)),
        true,
    );
    put(
        g,
        "header missing descr".into(),
        matloc_data::images::npy_with_header(
            &format!("{{'fortran_order': False, 'shape': {shape}, }}"),
            1,
            &f4(5.0),
        ),
        true,
    );
    put(
        g,
        "header python code".into(),
        matloc_data::images::npy_with_header(
            "{'descr': __import__('os').system('true'), 'fortran_order': False, 'shape': (1, 1), }",
            1,
            &f4(5.0),
        ),
        true,
    );
    put(
        g,
        "header invalid UTF-8".into(),
        matloc_data::images::npy_with_header("{'descr': '<f4\u{fffd}', }", 1, &f4(5.0)),
        true,
    );
    put(g, "empty file".into(), Vec::new(), true);
}

// ---------------------------------------------------------------------------------------------
// PLY point clouds

fn ply_cases(g: &mut Gen, base: &Base) {
    const C: &str = "ply";
    // A dataset without depth files that names its point cloud.
    let mut t = base.transforms.clone();
    for f in t["frames"].as_array_mut().unwrap() {
        f.as_object_mut().unwrap().remove("depth_file_path");
    }
    t["ply_file_path"] = json!("points.ply");
    let tbytes = serde_json::to_vec_pretty(&t).unwrap();
    let header = |n: &str, props: &str, format: &str| {
        format!("ply\nformat {format} 1.0\nelement vertex {n}\n{props}end_header\n")
    };
    let xyz = "property float x\nproperty float y\nproperty float z\n";
    let mut binary = header("100", xyz, "binary_little_endian").into_bytes();
    for i in 0..100 {
        for v in [i as f32, -(i as f32), 0.5] {
            binary.extend_from_slice(&v.to_le_bytes());
        }
    }
    let ascii_body: String = (0..50).map(|i| format!("{i} {} 0.5\n", -i)).collect();
    let ascii = header("50", xyz, "ascii") + &ascii_body;
    let mut cases: Vec<(String, Vec<u8>, bool)> = vec![
        ("valid binary".into(), binary.clone(), false),
        ("valid ascii".into(), ascii.clone().into_bytes(), false),
        ("no magic".into(), ascii.replacen("ply\n", "", 1).into_bytes(), true),
        ("big endian".into(), header("100", xyz, "binary_big_endian").into_bytes().into_iter().chain(binary[binary.len() - 1200..].iter().copied()).collect(), false),
        ("unknown format".into(), header("1", xyz, "utf7").into_bytes(), true),
        ("vertex count 10^18".into(), header("1000000000000000000", xyz, "binary_little_endian").into_bytes(), true),
        ("vertex count 2^64".into(), header("18446744073709551616", xyz, "binary_little_endian").into_bytes(), true),
        ("vertex count -1".into(), header("-1", xyz, "ascii").into_bytes(), true),
        ("no x property".into(), (header("2", "property float y\nproperty float z\n", "ascii") + "1 2\n3 4\n").into_bytes(), true),
        ("x as a list".into(), (header("1", "property list uchar float x\nproperty float y\nproperty float z\n", "ascii") + "2 1 2 3 4\n").into_bytes(), false),
        ("unknown property type".into(), (header("1", "property quad x\nproperty float y\nproperty float z\n", "ascii") + "1 2 3\n").into_bytes(), true),
        ("double and int types".into(), (header("1", "property double x\nproperty int y\nproperty uchar z\n", "ascii") + "1.5 2 3\n").into_bytes(), false),
        ("ascii NaN".into(), (header("2", xyz, "ascii") + "nan nan nan\n1 2 3\n").into_bytes(), false),
        ("ascii inf".into(), (header("2", xyz, "ascii") + "inf 0 0\n1 2 3\n").into_bytes(), false),
        ("ascii too few values".into(), (header("2", xyz, "ascii") + "1 2\n").into_bytes(), true),
        ("ascii text values".into(), (header("1", xyz, "ascii") + "a b c\n").into_bytes(), true),
        ("no end_header".into(), header("1", xyz, "ascii").replace("end_header\n", "").into_bytes(), true),
        ("empty".into(), Vec::new(), true),
        ("list element before vertex".into(), (String::from("ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int vertex_indices\n") + &header("1", xyz, "ascii")[19..] + "3 0 0 0\n1 2 3\n").into_bytes(), false),
        ("list length 255 past the end".into(), (String::from("ply\nformat binary_little_endian 1.0\nelement face 1\nproperty list uchar int vertex_indices\nelement vertex 1\n") + xyz + "end_header\n").into_bytes().into_iter().chain([255u8, 1, 2]).collect(), true),
        ("huge header line".into(), format!("ply\nformat ascii 1.0\ncomment {}\n", "x".repeat(1 << 20)).into_bytes(), true),
    ];
    for cut in cuts(binary.len(), 8).into_iter().skip(1) {
        cases.push((
            format!("binary truncated at {cut}"),
            binary[..cut].to_vec(),
            true,
        ));
    }
    for (label, bytes, must) in cases {
        let dir = g.dir(C);
        base.dataset(&dir, &tbytes);
        fs::write(dir.join("points.ply"), bytes).unwrap();
        g.info(C, label, dir.clone(), &dir, must, &["points.ply"]);
    }
    let dir = g.dir(C);
    base.dataset(&dir, &tbytes);
    link(Path::new("/dev/zero"), &dir.join("points.ply"));
    g.info(
        C,
        "points.ply is /dev/zero",
        dir.clone(),
        &dir,
        true,
        &["points.ply"],
    );
}

// ---------------------------------------------------------------------------------------------
// Mega-NeRF / .pt

fn meganerf_cases(g: &mut Gen, base: &Base) {
    const C: &str = "mega-nerf";
    let mut ds = read_dataset(&base.data).unwrap();
    ds.frames.truncate(FRAMES);
    let source = g.root.join("mega-nerf-source");
    write_mega_nerf(&ds, &source).unwrap();
    let coordinates = fs::read(source.join("coordinates.pt")).unwrap();
    let meta_dir = source.join("train/metadata");
    let mut metas: Vec<PathBuf> = fs::read_dir(&meta_dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    metas.sort();
    let meta_name = metas[0].file_name().unwrap().to_string_lossy().into_owned();
    let meta = fs::read(&metas[0]).unwrap();
    // A copy of the source with one file replaced.
    let copy = |g: &Gen, rel: &str, bytes: Option<&[u8]>| -> PathBuf {
        let dir = g.dir(C);
        copy_tree(&source, &dir);
        let p = dir.join(rel);
        let _ = fs::remove_file(&p);
        match bytes {
            Some(b) => fs::write(&p, b).unwrap(),
            None => link(Path::new("/dev/zero"), &p),
        }
        dir
    };
    let rel_meta = format!("train/metadata/{meta_name}");
    for (rel, bytes, name) in [
        ("coordinates.pt", &coordinates, "coordinates.pt"),
        (rel_meta.as_str(), &meta, meta_name.as_str()),
    ] {
        for cut in cuts(bytes.len(), 8) {
            let dir = copy(g, rel, Some(&bytes[..cut]));
            g.info(
                C,
                format!("{name} truncated at {cut}"),
                dir.clone(),
                &dir,
                true,
                &[name],
            );
        }
        for at in cuts(bytes.len(), 8).into_iter().skip(1) {
            let mut b = bytes.clone();
            for x in &mut b[at..(at + 6).min(bytes.len())] {
                *x ^= 0xa5;
            }
            let dir = copy(g, rel, Some(&b));
            g.info(
                C,
                format!("{name} corrupted at {at}"),
                dir.clone(),
                &dir,
                false,
                &[name],
            );
        }
        let dir = copy(g, rel, None);
        g.info(
            C,
            format!("{name} is /dev/zero"),
            dir.clone(),
            &dir,
            true,
            &[name],
        );
        let dir = copy(g, rel, Some(b"PK\x03\x04 not really a zip"));
        g.info(
            C,
            format!("{name} fake zip"),
            dir.clone(),
            &dir,
            true,
            &[name],
        );
    }
    let dir = g.dir(C);
    copy_tree(&source, &dir);
    for e in fs::read_dir(dir.join("train/rgbs")).unwrap() {
        fs::remove_file(e.unwrap().path()).unwrap();
    }
    g.info(C, "images missing", dir.clone(), &dir, true, &[]);
    let dir = g.dir(C);
    copy_tree(&source, &dir);
    fs::remove_dir_all(dir.join("train/metadata")).unwrap();
    g.info(
        C,
        "metadata directory missing",
        dir.clone(),
        &dir,
        true,
        &[],
    );
}

// ---------------------------------------------------------------------------------------------
// Map directories

fn map_cases(g: &mut Gen) {
    const C: &str = "map-dir";
    let partition = b"{\"version\": 1}".to_vec();
    let manifest = |files: Value, stages: Value| {
        json!({
            "format": "matloc-map",
            "version": 2,
            "created_by": "hostile corpus",
            "config": {},
            "scene": null,
            "blocks": [{"id": 0, "bounds_min": [0.0, 0.0, 0.0], "bounds_max": [1.0, 1.0, 1.0], "num_poses": 3, "selected_dims": []}],
            "stages": stages,
            "files": files,
        })
    };
    let good_files =
        json!({"partition.json": {"bytes": partition.len(), "sha256": sha256_hex(&partition)}});
    let good_stages = json!([{"name": "partition", "seconds": 1.0}]);
    let good = manifest(good_files.clone(), good_stages.clone());
    let mut cases: Vec<(String, Option<Vec<u8>>, bool)> = Vec::new();
    let v = |x: &Value| Some(serde_json::to_vec_pretty(x).unwrap());
    cases.push(("incomplete map".into(), v(&good), true));
    cases.push(("no manifest".into(), None, true));
    cases.push(("empty manifest".into(), Some(Vec::new()), true));
    cases.push((
        "manifest garbage".into(),
        Some(vec![0xde, 0xad, 0xbe, 0xef, 0, 1, 2]),
        true,
    ));
    cases.push(("manifest is an array".into(), Some(b"[]".to_vec()), true));
    let with = |key: &str, val: Value| {
        let mut m = good.clone();
        m[key] = val;
        m
    };
    for (key, val) in [
        ("format", json!("not-a-map")),
        ("format", json!(7)),
        ("version", json!(0)),
        ("version", json!(99)),
        ("version", json!("2")),
        ("version", json!(-1)),
        ("version", json!(1e300)),
        ("blocks", json!("many")),
        ("blocks", json!([{"id": "zero"}])),
        (
            "blocks",
            json!([{"id": 0, "bounds_min": [0, 0], "bounds_max": [1, 1, 1], "num_poses": 1, "selected_dims": []}]),
        ),
        ("stages", json!({"partition": 1})),
        ("stages", json!([{"name": 5, "seconds": 1}])),
        (
            "stages",
            json!([{"name": "nerf/0", "seconds": 1}, {"name": "nerf/99999", "seconds": 1}]),
        ),
        ("stages", json!([{"name": "partition", "seconds": "fast"}])),
        ("files", json!([])),
        (
            "files",
            json!({"partition.json": {"bytes": -1, "sha256": "00"}}),
        ),
        (
            "files",
            json!({"partition.json": {"bytes": partition.len(), "sha256": "not hex"}}),
        ),
        (
            "files",
            json!({"partition.json": {"bytes": 18_446_744_073_709_551_615u64, "sha256": sha256_hex(&partition)}}),
        ),
        (
            "files",
            json!({"partition.json": {"bytes": partition.len() + 1, "sha256": sha256_hex(&partition)}}),
        ),
        (
            "files",
            json!({"partition.json": {"bytes": 1u64 << 40, "sha256": sha256_hex(&partition)}}),
        ),
        (
            "files",
            json!({"partition.json": {"bytes": partition.len(), "sha256": sha256_hex(b"other")}}),
        ),
        (
            "files",
            json!({"../../../../etc/passwd": {"bytes": 1, "sha256": "00"}}),
        ),
        (
            "files",
            json!({"/etc/passwd": {"bytes": 1, "sha256": "00"}}),
        ),
        (
            "files",
            json!({"": {"bytes": 0, "sha256": sha256_hex(b"")}}),
        ),
        (
            "files",
            json!({"missing.bin": {"bytes": 10, "sha256": sha256_hex(b"0123456789")}}),
        ),
        (
            "files",
            json!({"blocks": {"bytes": 0, "sha256": sha256_hex(b"")}}),
        ),
        (
            "files",
            json!({"zero.bin": {"bytes": 1024, "sha256": sha256_hex(b"")}}),
        ),
        ("files", json!({})),
        ("config", json!("not an object")),
        ("split", json!({"every": "n"})),
    ] {
        cases.push((format!("{key} = {val}"), v(&with(key, val)), true));
    }
    let full = serde_json::to_vec_pretty(&good).unwrap();
    for cut in cuts(full.len(), 6).into_iter().skip(1) {
        cases.push((
            format!("manifest truncated at {cut}"),
            Some(full[..cut].to_vec()),
            true,
        ));
    }
    cases.push((
        "manifest nested 100000 deep".into(),
        Some("[".repeat(100_000).into_bytes()),
        true,
    ));
    cases.push(("manifest with a million blocks".into(), {
        let mut m = good.clone();
        m["blocks"] = Value::Array((0..1_000_000).map(|i| json!({"id": i, "bounds_min": [0, 0, 0], "bounds_max": [1, 1, 1], "num_poses": 1, "selected_dims": []})).take(200_000).collect());
        v(&m)
    }, true));
    for (label, bytes, must) in cases {
        for cmd in ["verify", "info"] {
            let dir = g.dir(C);
            let map = dir.join("map");
            fs::create_dir_all(map.join("blocks")).unwrap();
            fs::write(map.join("partition.json"), &partition).unwrap();
            link(Path::new("/dev/zero"), &map.join("zero.bin"));
            if let Some(b) = &bytes {
                fs::write(map.join("manifest.json"), b).unwrap();
            }
            let args = vec!["map".into(), cmd.into(), map.as_os_str().to_owned()];
            g.push(
                C,
                format!("map {cmd}: {label}"),
                dir,
                args,
                must,
                vec!["map".into()],
            );
        }
    }
    for (label, make) in [
        ("manifest is /dev/zero", 0),
        ("manifest is a directory", 1),
        ("map is a file", 2),
        ("map does not exist", 3),
        ("manifest is a FIFO", 4),
    ] {
        for cmd in ["verify", "info"] {
            let dir = g.dir(C);
            let map = dir.join("map");
            match make {
                0 => {
                    fs::create_dir_all(&map).unwrap();
                    link(Path::new("/dev/zero"), &map.join("manifest.json"));
                }
                1 => fs::create_dir_all(map.join("manifest.json")).unwrap(),
                2 => fs::write(&map, b"x").unwrap(),
                3 => {}
                _ => {
                    fs::create_dir_all(&map).unwrap();
                    let status = std::process::Command::new("mkfifo")
                        .arg(map.join("manifest.json"))
                        .status()
                        .unwrap();
                    assert!(status.success());
                }
            }
            let args = vec!["map".into(), cmd.into(), map.as_os_str().to_owned()];
            g.push(
                C,
                format!("map {cmd}: {label}"),
                dir,
                args,
                true,
                vec!["map".into()],
            );
        }
    }
}

// ---------------------------------------------------------------------------------------------
// A built map whose files are replaced consistently: the manifest's size and checksum updated
// with them, so only parsing the files finds what is wrong.

/// A safetensors container's header (JSON) and the byte offset its data starts at.
fn safetensors_header(bytes: &[u8]) -> (Value, usize) {
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    (serde_json::from_slice(&bytes[8..8 + n]).unwrap(), 8 + n)
}

/// A safetensors container with `header` and the data bytes `data`.
fn safetensors_bytes(header: &Value, data: &[u8]) -> Vec<u8> {
    let mut h = serde_json::to_vec(header).unwrap();
    while !h.len().is_multiple_of(8) {
        h.push(b' ');
    }
    let mut out = (h.len() as u64).to_le_bytes().to_vec();
    out.extend_from_slice(&h);
    out.extend_from_slice(data);
    out
}

/// Replaces map file `name` with `bytes` and updates its manifest entry to match.
fn replace_consistently(map: &Path, name: &str, bytes: &[u8]) {
    fs::write(map.join(name), bytes).unwrap();
    let path = map.join("manifest.json");
    let mut m: Value = serde_json::from_slice(&fs::read(&path).unwrap()).unwrap();
    m["files"][name] = json!({"bytes": bytes.len(), "sha256": sha256_hex(bytes)});
    fs::write(&path, serde_json::to_vec_pretty(&m).unwrap()).unwrap();
}

fn built_map_cases(g: &mut Gen, base: &Base) {
    const C: &str = "map-content";
    let built = g.root.join(C).join("built");
    let config = g.root.join(C).join("config.json");
    fs::create_dir_all(&built).unwrap();
    fs::write(&config, CHEAP_MAP_CONFIG).unwrap();
    let out = Command::new(super_bin())
        .args(["map", "build", "--quiet", "--data"])
        .arg(&base.data)
        .arg("--out")
        .arg(built.join("map"))
        .arg("--config")
        .arg(&config)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "building the corpus map: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let source = built.join("map");
    let model = "blocks/0/model.safetensors";
    let weights = fs::read(source.join(model)).unwrap();
    let (header, data_at) = safetensors_header(&weights);
    let hash = &header["hash_table"]["data_offsets"];
    let (h0, h1) = (
        data_at + hash[0].as_u64().unwrap() as usize,
        data_at + hash[1].as_u64().unwrap() as usize,
    );
    let mut nan = weights.clone();
    for c in nan[h0..h1].chunks_exact_mut(4) {
        c.copy_from_slice(&f32::NAN.to_le_bytes());
    }
    let mut reshaped = header.clone();
    let shape = reshaped["geo.0.weight"]["shape"]
        .as_array()
        .unwrap()
        .clone();
    reshaped["geo.0.weight"]["shape"] = json!([shape[1], shape[0]]);
    let reshaped = safetensors_bytes(&reshaped, &weights[data_at..]);
    let model_json = fs::read(source.join("blocks/0/model.json")).unwrap();
    let mut selection: Value =
        serde_json::from_slice(&fs::read(source.join("blocks/0/selection.json")).unwrap()).unwrap();
    selection["dims"][0] = json!(1_000_000);
    let mut partition: Value =
        serde_json::from_slice(&fs::read(source.join("partition.json")).unwrap()).unwrap();
    partition["blocks"] = json!([]);
    let encoder = fs::read(source.join("blocks/0/encoder.safetensors")).unwrap();
    let mut encoder_nan = encoder.clone();
    let (eh, e_at) = safetensors_header(&encoder);
    let bias = &eh["head.out.bias"]["data_offsets"];
    let at = e_at + bias[0].as_u64().unwrap() as usize;
    encoder_nan[at..at + 4].copy_from_slice(&f32::INFINITY.to_le_bytes());
    let cases: Vec<(&str, &str, Vec<u8>, Vec<&str>)> = vec![
        (
            "model.safetensors truncated at half",
            model,
            weights[..weights.len() / 2].to_vec(),
            vec!["model.safetensors", "header"],
        ),
        (
            "model.safetensors hash table NaN",
            model,
            nan,
            vec!["model.safetensors", "hash_table", "not finite"],
        ),
        (
            "model.safetensors geo.0.weight transposed",
            model,
            reshaped,
            vec!["model.safetensors", "geo.0.weight"],
        ),
        (
            "encoder.safetensors with one infinite bias",
            "blocks/0/encoder.safetensors",
            encoder_nan,
            vec!["encoder.safetensors", "head.out.bias", "not finite"],
        ),
        (
            "half model.json",
            "blocks/0/model.json",
            model_json[..model_json.len() / 2].to_vec(),
            vec!["model.json"],
        ),
        (
            "empty partition.json",
            "partition.json",
            Vec::new(),
            vec!["partition.json"],
        ),
        (
            "partition.json without blocks",
            "partition.json",
            serde_json::to_vec_pretty(&partition).unwrap(),
            vec!["partition.json", "blocks"],
        ),
        (
            "selection naming dim 1000000",
            "blocks/0/selection.json",
            serde_json::to_vec_pretty(&selection).unwrap(),
            vec!["selection.json", "dims", "1000000"],
        ),
    ];
    for cmd in ["verify", "info"] {
        let dir = g.dir(C);
        copy_tree(&source, &dir.join("map"));
        let args = vec!["map".into(), cmd.into(), dir.join("map").into_os_string()];
        g.push(
            C,
            format!("map {cmd}: the built map (control)"),
            dir,
            args,
            false,
            vec![],
        );
    }
    for (label, name, bytes, names) in &cases {
        for cmd in ["verify", "info"] {
            let dir = g.dir(C);
            let map = dir.join("map");
            copy_tree(&source, &map);
            replace_consistently(&map, name, bytes);
            let args = vec!["map".into(), cmd.into(), map.as_os_str().to_owned()];
            g.push(
                C,
                format!("map {cmd}: {label}"),
                dir,
                args,
                true,
                names.iter().map(|s| s.to_string()).collect(),
            );
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Build configs

fn config_cases(g: &mut Gen) {
    const C: &str = "config";
    let out = Command::new(super_bin())
        .args(["map", "config", "--print-default"])
        .output();
    let default: Value = match out {
        Ok(o) if o.status.success() => serde_json::from_slice(&o.stdout).unwrap(),
        _ => panic!("`matloc map config --print-default` failed"),
    };
    // Every object in the default config gets an unknown key; every leaf a value of the
    // wrong type. The build must stop at the config, naming the key.
    let mut paths: Vec<(Vec<String>, bool)> = Vec::new();
    fn walk(v: &Value, path: &mut Vec<String>, out: &mut Vec<(Vec<String>, bool)>) {
        match v {
            Value::Object(m) => {
                out.push((path.clone(), true));
                for (k, child) in m {
                    if k == "model_overrides" {
                        continue;
                    }
                    path.push(k.clone());
                    walk(child, path, out);
                    path.pop();
                }
            }
            _ => out.push((path.clone(), false)),
        }
    }
    walk(&default, &mut Vec::new(), &mut paths);
    let run = |g: &mut Gen, label: String, bytes: &[u8], names: Vec<String>| {
        let dir = g.dir(C);
        let file = dir.join("config.json");
        fs::write(&file, bytes).unwrap();
        let args: Vec<OsString> = vec![
            "map".into(),
            "build".into(),
            "--data".into(),
            dir.join("no-such-dataset").into_os_string(),
            "--out".into(),
            dir.join("map").into_os_string(),
            "--config".into(),
            file.into_os_string(),
        ];
        g.push(C, label, dir, args, true, names);
    };
    for (path, is_object) in paths {
        let mut c = default.clone();
        let mut at = &mut c;
        for k in &path {
            at = &mut at[k.as_str()];
        }
        let dotted = path.join(".");
        if is_object {
            at["hostile_key"] = json!(1);
            run(
                g,
                format!("unknown key in `{dotted}`"),
                &serde_json::to_vec(&c).unwrap(),
                vec!["config.json".into(), "hostile_key|expected".into()],
            );
        } else {
            let replacement = match at {
                Value::String(_) => json!(12345),
                Value::Null => json!({"x": [1]}),
                Value::Bool(_) => json!("yes"),
                Value::Array(_) => json!("list"),
                _ => json!("a string"),
            };
            *at = replacement;
            // serde names the expected type and the position, not the key.
            run(
                g,
                format!("wrong type at `{dotted}`"),
                &serde_json::to_vec_pretty(&c).unwrap(),
                vec!["config.json".into()],
            );
        }
    }
    for (label, bytes) in [
        ("empty file", Vec::new()),
        ("not JSON", b"nerf.steps = 3".to_vec()),
        ("array", b"[]".to_vec()),
        ("NaN", b"{\"nerf\": {\"steps\": NaN}}".to_vec()),
        ("negative steps", b"{\"nerf\": {\"steps\": -5}}".to_vec()),
        (
            "steps 2^64",
            b"{\"nerf\": {\"steps\": 18446744073709551616}}".to_vec(),
        ),
        ("nested 100000 deep", "{\"a\":".repeat(100_000).into_bytes()),
        ("truncated", b"{\"nerf\": {\"steps\"".to_vec()),
    ] {
        run(g, label.into(), &bytes, vec!["config.json".into()]);
        // A top-level `[]` reads as a struct with every field defaulted.
        if label == "array" {
            let case = g.cases.last_mut().unwrap();
            case.must_fail = false;
            case.names.clear();
        }
    }
}

use std::process::Command;

fn super_bin() -> PathBuf {
    if let Some(p) = std::env::var_os("MATLOC_BIN") {
        return PathBuf::from(p);
    }
    let exe = std::env::current_exe().unwrap();
    exe.parent().unwrap().parent().unwrap().join("matloc")
}
