//! A built map loaded and validated: its blocks (renderer, query encoder, matcher, selected
//! dims), the place predictor, the pose solver and the calibrated confidence, each behind its
//! stage trait. [`MapComponents`] makes those objects from what the build stored;
//! [`NerfMapComponents`] reads this crate's own map format, and another implementation can
//! serve the same map directory with other renderers, encoders, matchers, place predictors or
//! solvers ([`LoadedMap::open_with`]).
//!
//! A process can load a subset of the blocks ([`LoadedMap::open_blocks`]): the others keep
//! their place (block ids stay the map's) as [`MapBlock::unserved`] stand-ins that hold no
//! model, and a query whose best place hypothesis falls in one of them is tried on that
//! hypothesis only, which fails naming the block. That is what lets a large map be split over
//! processes by block, each answering the queries the place predictor sends to its blocks.

use std::path::Path;
use std::sync::Arc;

use matloc_core::{Camera, Image, Pose};
use matloc_encoder::QueryEncoder;
use matloc_match::nerf_view::NerfViewRenderer;
use matloc_match::{
    FeatureStats, Match2d3d, MatchError, Matcher, MnnConfig, MnnMatcher, QueryFeatures,
    RenderFailure, RenderedPoints, RenderedView, ViewRenderer,
};
use matloc_partition::Partition;
use matloc_place::{PlaceError, PlaceHypothesis, PlaceModel, PlacePredictor};
use matloc_pnp::{LoRansacPnp, PoseSolver};
use matloc_render::NerfModel;

use crate::config::MapConfig;
use crate::error::PipelineError;
use crate::localizer::confidence::ConfidenceModel;
use crate::localizer::options::LocalizeOptions;
use crate::localizer::{Localizer, LocalizerBlock, QueryFeatureEncoder, positions_of};
use crate::map::layout::{
    CONFIDENCE_FILE, CalibrationRecord, PARTITION_FILE, PLACE_DIR, SelectionRecord, block_dir,
    encoder_file, selection_file,
};
use crate::map::manifest::{MapDir, MapError};

/// `model` rendering with `steps` march steps per ray (0 = unchanged).
fn with_render_steps(model: NerfModel, steps: usize) -> Result<NerfModel, PipelineError> {
    if steps == 0 {
        return Ok(model);
    }
    let mut view = model.config().render;
    view.march.steps = steps;
    Ok(model.with_view_config(view)?)
}

/// Block `b`'s NeRF; `render_steps > 0` replaces its ray-marching grid.
pub(crate) fn load_nerf(
    map: &MapDir,
    b: usize,
    render_steps: usize,
) -> Result<NerfViewRenderer, PipelineError> {
    let dir = map.path_of(&block_dir(b))?;
    let model = with_render_steps(NerfModel::load(&dir)?, render_steps)?;
    Ok(NerfViewRenderer::new(model, block_dir(b)))
}

/// Block `b`'s query encoder, read through the map so its checksum is verified.
pub(crate) fn load_encoder(map: &MapDir, b: usize) -> Result<QueryEncoder, PipelineError> {
    let name = encoder_file(b);
    map.read_file(&name)?;
    Ok(QueryEncoder::load(&map.path_of(&name)?)?)
}

/// The matching window of a map (see [`LocalizeOptions::window_fraction`]), for a grid as
/// wide as the map's images.
pub(crate) fn window_px(map: &MapDir, options: &LocalizeOptions) -> Option<f64> {
    let width = scene_camera(map).map_or(320.0, |c| c.width as f64);
    (options.window_fraction > 0.0).then_some(options.window_fraction * width)
}

/// The camera of the map's training images as recorded at build time (the first one's).
fn scene_camera(map: &MapDir) -> Option<Camera> {
    map.manifest()
        .scene
        .get("camera")
        .and_then(|c| serde_json::from_value(c.clone()).ok())
}

/// A block's renderer as the localizer uses it, and the NeRF behind it when there is one (the
/// methods that render colour — the rgb-keypoints and iNeRF baselines — need the model).
pub struct BlockRenderer {
    /// Features and depth at a pose.
    pub renderer: Arc<dyn ViewRenderer>,
    /// The same renderer as a NeRF, if it is one.
    pub nerf: Option<Arc<NerfViewRenderer>>,
}

/// Makes a loaded map's stage objects from what its build stored.
pub trait MapComponents {
    /// Block `block`'s renderer, with the localizer's render settings.
    fn renderer(
        &self,
        map: &MapDir,
        block: usize,
        options: &LocalizeOptions,
    ) -> Result<BlockRenderer, PipelineError>;
    /// Block `block`'s query encoder.
    fn encoder(
        &self,
        map: &MapDir,
        block: usize,
    ) -> Result<Box<dyn QueryFeatureEncoder>, PipelineError>;
    /// A matcher for `encoder`'s output restricted to `dims`, within `window_px` (`None`:
    /// global).
    fn matcher(
        &self,
        encoder: &dyn QueryFeatureEncoder,
        dims: &[usize],
        window_px: Option<f64>,
    ) -> Result<Box<dyn Matcher>, PipelineError>;
    /// The place predictor, configured as the build says.
    fn place(
        &self,
        map: &MapDir,
        config: &MapConfig,
    ) -> Result<Box<dyn PlacePredictor + Send + Sync>, PipelineError>;
    /// The pose solver with the map's options.
    fn solver(&self, options: &LocalizeOptions) -> Box<dyn PoseSolver + Send + Sync>;
}

/// The components of this crate's map format: sub-NeRFs ([`NerfViewRenderer`]), the burn
/// query encoder, the mutual-nearest-neighbour matcher normalised with the encoder's feature
/// statistics, the ArcFace place classifier and P3P in LO-RANSAC with
/// [`LocalizeOptions::pnp`].
#[derive(Clone, Copy, Debug, Default)]
pub struct NerfMapComponents;

impl MapComponents for NerfMapComponents {
    fn renderer(
        &self,
        map: &MapDir,
        block: usize,
        options: &LocalizeOptions,
    ) -> Result<BlockRenderer, PipelineError> {
        let nerf = Arc::new(load_nerf(map, block, options.render_steps)?);
        Ok(BlockRenderer {
            renderer: nerf.clone(),
            nerf: Some(nerf),
        })
    }

    fn encoder(
        &self,
        map: &MapDir,
        block: usize,
    ) -> Result<Box<dyn QueryFeatureEncoder>, PipelineError> {
        Ok(Box::new(load_encoder(map, block)?))
    }

    fn matcher(
        &self,
        encoder: &dyn QueryFeatureEncoder,
        dims: &[usize],
        window_px: Option<f64>,
    ) -> Result<Box<dyn Matcher>, PipelineError> {
        Ok(Box::new(block_matcher(encoder, dims, window_px)?))
    }

    fn place(
        &self,
        map: &MapDir,
        config: &MapConfig,
    ) -> Result<Box<dyn PlacePredictor + Send + Sync>, PipelineError> {
        map.read_file(&format!("{PLACE_DIR}/{}", matloc_place::MODEL_WEIGHTS))?;
        let mut place = PlaceModel::load(&map.path_of(PLACE_DIR)?)?;
        config.place.configure(&mut place);
        Ok(Box::new(place))
    }

    fn solver(&self, options: &LocalizeOptions) -> Box<dyn PoseSolver + Send + Sync> {
        Box::new(LoRansacPnp::new(options.pnp.clone()))
    }
}

/// One block of a loaded map.
pub struct MapBlock {
    /// Features and depth of the block (its sub-NeRF in this crate's maps).
    pub renderer: Arc<dyn ViewRenderer>,
    /// The sub-NeRF itself, when the renderer is one.
    pub nerf: Option<Arc<NerfViewRenderer>>,
    /// Query image → this block's feature domain.
    pub encoder: Box<dyn QueryFeatureEncoder>,
    /// Matcher normalising with this block's feature statistics (windowed when
    /// [`LocalizeOptions::window_fraction`] is positive).
    pub matcher: Box<dyn Matcher>,
    /// Rendered dims (the matcher's feature space; see [`LocalizerBlock::dims`]).
    pub dims: Vec<usize>,
    /// Selected dims matched on, when fewer than `dims`.
    pub match_dims: Option<Vec<usize>>,
    /// Whether this process serves the block (`false`: a [`MapBlock::unserved`] stand-in).
    pub served: bool,
}

/// A block that is not loaded ([`LoadedMap::open_blocks`]): it renders nothing (the
/// localizer records the hypothesis as failed with a message naming the block and goes on),
/// encodes to an empty map and matches nothing.
struct UnservedBlock {
    block: usize,
}

impl UnservedBlock {
    fn message(&self) -> String {
        format!("block {} is not served by this process", self.block)
    }
}

impl ViewRenderer for UnservedBlock {
    fn num_features(&self) -> usize {
        0
    }

    fn describe(&self) -> String {
        self.message()
    }

    fn render_view(
        &self,
        _camera: &Camera,
        _cam_from_world: &Pose,
        _stride: u32,
        _dims: &[usize],
    ) -> Result<RenderedView, RenderFailure> {
        Err(self.message().into())
    }
}

impl QueryFeatureEncoder for UnservedBlock {
    fn dims(&self) -> &[usize] {
        &[]
    }

    fn stride(&self) -> u32 {
        1
    }

    fn encode(&self, _image: &Image<f32>) -> Result<matloc_core::FeatureMap, PipelineError> {
        Ok(Image::new(0, 0, 0))
    }

    fn stats(&self) -> Option<&FeatureStats> {
        None
    }
}

impl Matcher for UnservedBlock {
    fn match_features(
        &self,
        _query: &QueryFeatures,
        _map: &RenderedPoints,
        _selection: Option<&[usize]>,
    ) -> Result<Vec<Match2d3d>, MatchError> {
        Ok(Vec::new())
    }
}

/// The map's place predictor in a process that serves some blocks: when the best hypothesis
/// falls in a block it does not serve, only that hypothesis is returned, so the localizer
/// refuses the query at once (naming the block) instead of trying lower-ranked places that
/// another process may serve better.
struct ServedPlace {
    inner: Box<dyn PlacePredictor + Send + Sync>,
    served: Vec<bool>,
}

impl PlacePredictor for ServedPlace {
    fn predict(
        &self,
        image: &Image<f32>,
        camera: &Camera,
        k: usize,
    ) -> Result<Vec<PlaceHypothesis>, PlaceError> {
        let mut hyps = self.inner.predict(image, camera, k)?;
        if let Some(first) = hyps.first()
            && !self
                .served
                .get(first.block.unwrap_or(0))
                .copied()
                .unwrap_or(false)
        {
            hyps.truncate(1);
        }
        Ok(hyps)
    }
}

/// The MNN matcher of a block for matching on `dims`: the encoder's feature statistics
/// restricted to them (the matcher sees only those dims; none when the encoder has none),
/// windowed to `window_px`.
pub fn block_matcher(
    encoder: &dyn QueryFeatureEncoder,
    dims: &[usize],
    window_px: Option<f64>,
) -> Result<MnnMatcher, PipelineError> {
    let stats = match encoder.stats() {
        Some(full) => {
            let channels = positions_of(dims, encoder.dims())?;
            Some(FeatureStats {
                mean: channels.iter().map(|&c| full.mean[c]).collect(),
                std: channels.iter().map(|&c| full.std[c]).collect(),
            })
        }
        None => None,
    };
    Ok(MnnMatcher::new(MnnConfig {
        stats,
        window_px,
        ..MnnConfig::default()
    }))
}

impl MapBlock {
    /// Loads block `b` with `components`: its renderer (render settings of `options`), its
    /// encoder, and a matcher windowed as `options` say on the dims `dims` picks from the
    /// encoder's dims (rendered dims, and the matched subset when smaller).
    pub fn load(
        map: &MapDir,
        b: usize,
        options: &LocalizeOptions,
        components: &dyn MapComponents,
        dims: impl FnOnce(&[usize]) -> (Vec<usize>, Option<Vec<usize>>),
    ) -> Result<Self, PipelineError> {
        let BlockRenderer { renderer, nerf } = components.renderer(map, b, options)?;
        let encoder = components.encoder(map, b)?;
        let (dims, match_dims) = dims(encoder.dims());
        let matcher = components.matcher(encoder.as_ref(), &dims, window_px(map, options))?;
        Ok(MapBlock {
            renderer,
            nerf,
            encoder,
            matcher,
            dims,
            match_dims,
            served: true,
        })
    }

    /// The stand-in of block `b` when this process does not serve it: no model is loaded;
    /// rendering it fails with "block `b` is not served by this process".
    pub fn unserved(b: usize) -> Self {
        MapBlock {
            renderer: Arc::new(UnservedBlock { block: b }),
            nerf: None,
            encoder: Box::new(UnservedBlock { block: b }),
            matcher: Box::new(UnservedBlock { block: b }),
            dims: Vec::new(),
            match_dims: None,
            served: false,
        }
    }

    /// This block as the localizer sees it.
    pub fn localizer_block(&self) -> LocalizerBlock<'_> {
        LocalizerBlock {
            renderer: self.renderer.as_ref(),
            encoder: self.encoder.as_ref(),
            matcher: self.matcher.as_ref(),
            dims: self.dims.clone(),
            match_dims: self.match_dims.clone(),
        }
    }
}

/// The blocks of a map, loaded.
pub struct LoadedBlocks(pub Vec<MapBlock>);

impl LoadedBlocks {
    /// Loads blocks `0..n` (renderer, encoder, selection) from `map` with `components`, with
    /// the matching window ([`LocalizeOptions::window_fraction`], for a grid as wide as the
    /// map's images) and the render sampling ([`LocalizeOptions::render_steps`]) of `options`.
    pub fn load(
        map: &MapDir,
        n: usize,
        options: &LocalizeOptions,
        components: &dyn MapComponents,
    ) -> Result<Self, PipelineError> {
        Self::load_served(map, n, None, options, components)
    }

    /// [`LoadedBlocks::load`] of the blocks in `served` only (`None`: all); the others are
    /// [`MapBlock::unserved`] stand-ins, so block ids keep indexing the list.
    pub fn load_served(
        map: &MapDir,
        n: usize,
        served: Option<&[usize]>,
        options: &LocalizeOptions,
        components: &dyn MapComponents,
    ) -> Result<Self, PipelineError> {
        let blocks = (0..n)
            .map(|b| {
                if served.is_some_and(|s| !s.contains(&b)) {
                    return Ok(MapBlock::unserved(b));
                }
                let sel: SelectionRecord = map.read_json(&selection_file(b))?;
                MapBlock::load(map, b, options, components, |encoded| {
                    if options.refine_on_all_dims && sel.dims.len() < encoded.len() {
                        (encoded.to_vec(), Some(sel.dims))
                    } else {
                        (sel.dims, None)
                    }
                })
            })
            .collect::<Result<_, PipelineError>>()?;
        Ok(Self(blocks))
    }

    /// A localizer over these blocks.
    pub fn localizer<'a>(
        &'a self,
        place: &'a dyn PlacePredictor,
        solver: &'a dyn PoseSolver,
        options: LocalizeOptions,
    ) -> Localizer<'a> {
        Localizer {
            place,
            blocks: self.0.iter().map(MapBlock::localizer_block).collect(),
            solver,
            options,
        }
    }
}

/// A built map, loaded and validated: everything localization and evaluation need.
pub struct LoadedMap {
    /// The map directory (manifest, checksums).
    pub dir: MapDir,
    /// The build configuration.
    pub config: MapConfig,
    /// The partition.
    pub partition: Partition,
    /// Blocks.
    pub blocks: LoadedBlocks,
    /// Place predictor.
    pub place: Box<dyn PlacePredictor + Send + Sync>,
    /// Pose solver.
    pub solver: Box<dyn PoseSolver + Send + Sync>,
    /// Calibrated confidence.
    pub confidence: ConfidenceModel,
    /// Calibrated bound on an accepted pose's rotation from its coarse pose (`None`: the
    /// configured one).
    pub max_accept_rotation_deg: Option<f64>,
    /// What the confidence was fitted on.
    pub calibrated_on: crate::config::CalibrationQueries,
    /// The keypoint structure of the training images, when the map has one (maps built
    /// before the structure stage, or with it disabled, do not).
    pub structure: Option<matloc_structure::StructureMap>,
}

impl LoadedMap {
    /// Opens a map with this crate's components ([`NerfMapComponents`]): validates the
    /// manifest and every checksum, checks that the build completed, and loads the models.
    pub fn open(root: &Path) -> Result<Self, PipelineError> {
        Self::open_with(root, &NerfMapComponents)
    }

    /// [`LoadedMap::open`] with other components.
    pub fn open_with(root: &Path, components: &dyn MapComponents) -> Result<Self, PipelineError> {
        Self::open_blocks_with(root, None, components)
    }

    /// [`LoadedMap::open`] loading only the blocks in `served` (`None`: all of them): the
    /// other blocks' NeRFs and encoders stay on disk (their checksums are still verified), and
    /// a query whose best place hypothesis is one of them is refused with that hypothesis's
    /// failure "block `b` is not served by this process" ([`LoadedMap::serves`]). A block id
    /// the partition does not have is [`PipelineError::Config`].
    pub fn open_blocks(root: &Path, served: Option<&[usize]>) -> Result<Self, PipelineError> {
        Self::open_blocks_with(root, served, &NerfMapComponents)
    }

    /// [`LoadedMap::open_blocks`] with other components.
    pub fn open_blocks_with(
        root: &Path,
        served: Option<&[usize]>,
        components: &dyn MapComponents,
    ) -> Result<Self, PipelineError> {
        let dir = MapDir::open(root)?;
        dir.verify()?;
        let config: MapConfig = serde_json::from_value(dir.manifest().config.clone())
            .map_err(|source| PipelineError::ManifestConfig { source })?;
        let complete = |blocks: usize| match dir.completeness(blocks).into_iter().next() {
            None => Ok(()),
            Some(MapError::StageMissing { stage }) => Err(PipelineError::Incomplete {
                root: root.to_path_buf(),
                stage,
            }),
            Some(e) => Err(e.into()),
        };
        complete(dir.manifest().blocks.len())?;
        let partition: Partition = dir.read_json(PARTITION_FILE)?;
        let n = partition.blocks.len();
        complete(n)?;
        if let Some(bad) = served.and_then(|s| s.iter().find(|&&b| b >= n)) {
            return Err(PipelineError::Config(format!(
                "block {bad} is not in the map (its partition has blocks 0..{n})"
            )));
        }
        let blocks = LoadedBlocks::load_served(&dir, n, served, &config.localize, components)?;
        let mut place = components.place(&dir, &config)?;
        if let Some(s) = served {
            place = Box::new(ServedPlace {
                inner: place,
                served: (0..n).map(|b| s.contains(&b)).collect(),
            });
        }
        let solver = components.solver(&config.localize);
        let record: CalibrationRecord = dir.read_json(CONFIDENCE_FILE)?;
        let structure = if dir.stage_done("structure") {
            let bytes = dir.read_file(crate::map::layout::STRUCTURE_FILE)?;
            Some(matloc_structure::StructureMap::from_bytes(
                &bytes,
                &root.join(crate::map::layout::STRUCTURE_FILE),
            )?)
        } else {
            None
        };
        Ok(Self {
            dir,
            config,
            partition,
            blocks,
            place,
            solver,
            confidence: record.model,
            max_accept_rotation_deg: record.max_accept_rotation_deg,
            calibrated_on: record.queries,
            structure,
        })
    }

    /// Localizer options: the stored ones with the calibrated confidence, and queries reduced
    /// to the map's working resolution unless the options set their own.
    pub fn options(&self) -> LocalizeOptions {
        let configured = self.config.localize.max_accept_rotation_deg;
        LocalizeOptions {
            confidence: self.confidence.clone(),
            max_accept_rotation_deg: self
                .max_accept_rotation_deg
                .map_or(configured, |b| b.min(configured)),
            max_side: self
                .config
                .localize
                .max_side
                .or(self.config.images.max_side),
            ..self.config.localize.clone()
        }
    }

    /// The MatLoc localizer over this map's place predictor, blocks and solver.
    pub fn localizer(&self) -> Localizer<'_> {
        self.blocks
            .localizer(self.place.as_ref(), self.solver.as_ref(), self.options())
    }

    /// The camera of the map's training images (the first one's), as recorded at build time:
    /// the resolution its query encoders were trained at.
    pub fn camera(&self) -> Option<Camera> {
        scene_camera(&self.dir)
    }

    /// Whether this process serves block `b` (it is in the map and was loaded).
    pub fn serves(&self, b: usize) -> bool {
        self.blocks.0.get(b).is_some_and(|m| m.served)
    }

    /// The blocks this process serves, in order.
    pub fn served_blocks(&self) -> Vec<usize> {
        (0..self.blocks.0.len())
            .filter(|&b| self.serves(b))
            .collect()
    }

    /// The NeRF of block `b`, when its renderer is one.
    pub fn nerf(&self, b: usize) -> Option<&NerfModel> {
        self.blocks
            .0
            .get(b)?
            .nerf
            .as_deref()
            .map(NerfViewRenderer::model)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use matloc_render::ModelConfig;

    #[test]
    fn render_steps_replace_only_the_march_grid() {
        let mut config = ModelConfig::for_scene([-4.0, -4.0, -1.0], [4.0, 4.0, 3.0], 5.0, 2);
        config.field.log2_table_size = 12;
        let model = NerfModel::new(config.clone()).unwrap();
        let same = with_render_steps(model.clone(), 0).unwrap();
        assert_eq!(same.config(), &config);
        let coarse = with_render_steps(model, 96).unwrap();
        assert_eq!(coarse.config().render.march.steps, 96);
        let mut expected = config;
        expected.render.march.steps = 96;
        assert_eq!(coarse.config(), &expected);
    }
}
