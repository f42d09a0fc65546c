//! `matloc dataset import`: convert another layout into a nerfstudio `transforms.json`.

use std::fs::File;
use std::io;
use std::path::{Component, Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};
use matloc_core::fsutil::write_atomic_with;
use matloc_data::meganerf::{MegaNerfOptions, read_mega_nerf_with};
use matloc_data::nerfstudio::{TRANSFORMS_JSON, write_nerfstudio};
use matloc_data::{Dataset, Split};

/// `matloc dataset import ...`
#[derive(Subcommand)]
pub enum ImportCommand {
    /// A Mega-NeRF / Mill-19 dataset (coordinates.pt, {train,val}/metadata, rgbs) → nerfstudio
    /// transforms.json with metric poses; train stays train, val becomes test.
    MegaNerf(MegaNerfArgs),
}

/// Arguments of `matloc dataset import mega-nerf`.
#[derive(Args)]
pub struct MegaNerfArgs {
    /// The Mega-NeRF dataset directory.
    pub dir: PathBuf,
    /// Output directory (created); receives transforms.json.
    #[arg(long)]
    pub out: PathBuf,
    /// Copy the images into OUT/images/{train,val}/ instead of referencing them by relative
    /// path.
    #[arg(long)]
    pub copy: bool,
    /// The rgbs/ hold the original, distorted photos: give the cameras the files' distortion
    /// (Mega-NeRF's own rgbs/ are undistorted).
    #[arg(long)]
    pub distorted_images: bool,
}

/// Runs `matloc dataset import ...`.
pub fn run(cmd: &ImportCommand) -> Result<()> {
    match cmd {
        ImportCommand::MegaNerf(a) => mega_nerf(a),
    }
}

fn mega_nerf(a: &MegaNerfArgs) -> Result<()> {
    let dataset = read_mega_nerf_with(
        &a.dir,
        &MegaNerfOptions {
            images_distorted: a.distorted_images,
        },
    )
    .with_context(|| format!("reading Mega-NeRF dataset {}", a.dir.display()))?;
    let written = import(&dataset, &a.out, a.copy)?;
    outln!(
        "imported {} frames ({} train, {} test) into {}",
        dataset.frames.len(),
        dataset.split(Split::Train).count(),
        dataset.split(Split::Test).count(),
        written.display()
    )?;
    Ok(())
}

/// Writes `dataset` as `out/transforms.json`, its frames referring to the images by paths
/// relative to `out`, or to copies in `out/images/` (each copied atomically). The
/// transforms file is written last and atomically, so a failed import leaves none.
fn import(dataset: &Dataset, out: &Path, copy: bool) -> Result<PathBuf> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let out_abs = out
        .canonicalize()
        .with_context(|| format!("resolving {}", out.display()))?;
    let root_abs = dataset
        .root
        .canonicalize()
        .with_context(|| format!("resolving {}", dataset.root.display()))?;
    let mut frames = dataset.frames.clone();
    for f in &mut frames {
        let source = root_abs.join(&f.image_path);
        f.image_path = if copy {
            // `train/rgbs/000000.jpg` → `images/train/000000.jpg`.
            let split_dir = f.image_path.components().next();
            let name = f.image_path.file_name();
            let (Some(Component::Normal(split_dir)), Some(name)) = (split_dir, name) else {
                bail!("unexpected image path {}", f.image_path.display());
            };
            let rel = Path::new("images").join(split_dir).join(name);
            let target = out_abs.join(&rel);
            if let Some(parent) = target.parent() {
                std::fs::create_dir_all(parent)
                    .with_context(|| format!("creating {}", parent.display()))?;
            }
            write_atomic_with(&target, |file| {
                io::copy(&mut File::open(&source)?, file).map(|_| ())
            })
            .with_context(|| format!("copying {} to {}", source.display(), target.display()))?;
            rel
        } else {
            relative_to(&source, &out_abs)
        };
    }
    let imported = Dataset {
        root: out.to_path_buf(),
        frames,
        metadata: dataset.metadata.clone(),
        points: None,
    };
    write_nerfstudio(&imported, out)
        .with_context(|| format!("writing {}", out.join(TRANSFORMS_JSON).display()))?;
    Ok(out.join(TRANSFORMS_JSON))
}

/// `target` as a path relative to the directory `base` (both absolute), with `..` where
/// needed; `target` itself when they share no root.
fn relative_to(target: &Path, base: &Path) -> PathBuf {
    let t: Vec<Component> = target.components().collect();
    let b: Vec<Component> = base.components().collect();
    let common = t.iter().zip(&b).take_while(|(x, y)| x == y).count();
    if common == 0 {
        return target.to_path_buf();
    }
    let mut rel = PathBuf::new();
    for _ in common..b.len() {
        rel.push("..");
    }
    for c in &t[common..] {
        rel.push(c.as_os_str());
    }
    rel
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn relative_paths_climb_out_of_the_base() {
        assert_eq!(
            relative_to(Path::new("/d/mega/train/rgbs/a.jpg"), Path::new("/d/out")),
            PathBuf::from("../mega/train/rgbs/a.jpg")
        );
        assert_eq!(
            relative_to(Path::new("/d/out/x/a.jpg"), Path::new("/d/out")),
            PathBuf::from("x/a.jpg")
        );
        assert_eq!(
            relative_to(Path::new("/a/b.jpg"), Path::new("/c/d/e")),
            PathBuf::from("../../../a/b.jpg")
        );
    }
}
