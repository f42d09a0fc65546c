use std::collections::HashMap;
use std::fs;
use std::path::{Path, PathBuf};

use safetensors::{Dtype, SafeTensors, tensor::TensorView};

use crate::config::FieldConfig;
use crate::error::FieldError;
use crate::field::NerfactoField;
use crate::hashgrid::HashGrid;
use crate::mlp::Linear;

const LAYER_NAMES: [&str; 5] = ["geo.0", "geo.1", "colour.0", "colour.1", "colour.2"];

/// Writes `bytes` to `path` atomically ([`matloc_core::fsutil::write_atomic`]).
fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), FieldError> {
    matloc_core::fsutil::write_atomic(path, bytes).map_err(|source| FieldError::Io {
        path: path.to_path_buf(),
        source,
    })
}

impl NerfactoField {
    /// Tensor names and shapes this field's config implies, in file order.
    ///
    /// Layer weights are stored input-major (`[n_in, n_out]`, i.e. the transpose of a
    /// PyTorch `Linear.weight`).
    pub fn tensor_shapes(config: &FieldConfig) -> Vec<(String, Vec<usize>)> {
        let levels = HashGrid::layout(
            config.log2_table_size,
            config.base_resolution,
            config.max_resolution,
        );
        let entries = levels.last().map_or(0, |l| l.offset + l.size);
        let ci = config.colour_input_dim();
        let dims = [(32, 64), (64, 16), (ci, 64), (64, 64), (64, 3)];
        let mut v = vec![("hash_table".to_string(), vec![entries, 2])];
        for (name, (i, o)) in LAYER_NAMES.iter().zip(dims) {
            v.push((format!("{name}.weight"), vec![i, o]));
            v.push((format!("{name}.bias"), vec![o]));
        }
        v.push((
            "appearance".to_string(),
            vec![config.num_images, config.appearance_dim],
        ));
        v
    }

    fn tensors(&self) -> Vec<(String, &[f32])> {
        let mut v: Vec<(String, &[f32])> = vec![("hash_table".into(), &self.grid.table)];
        for (name, l) in LAYER_NAMES
            .iter()
            .zip(self.geo.iter().chain(self.col.iter()))
        {
            v.push((format!("{name}.weight"), &l.w));
            v.push((format!("{name}.bias"), &l.b));
        }
        v.push(("appearance".into(), &self.appearance));
        v
    }

    /// Serialises the weights to safetensors bytes.
    pub fn to_safetensors_bytes(&self) -> Result<Vec<u8>, FieldError> {
        let shapes = Self::tensor_shapes(self.config());
        let data = self.tensors();
        let mut views = Vec::with_capacity(data.len());
        for ((name, shape), (_, vals)) in shapes.into_iter().zip(&data) {
            let view =
                TensorView::new(Dtype::F32, shape, bytemuck::cast_slice(vals)).map_err(|e| {
                    FieldError::Safetensors {
                        path: PathBuf::new(),
                        message: e.to_string(),
                    }
                })?;
            views.push((name, view));
        }
        let mut meta = HashMap::new();
        meta.insert("format".to_string(), "matloc-nerf-field/1".to_string());
        safetensors::serialize(views, Some(meta)).map_err(|e| FieldError::Safetensors {
            path: PathBuf::new(),
            message: e.to_string(),
        })
    }

    /// Saves weights (safetensors) and config (JSON), each written atomically.
    pub fn save(&self, weights_path: &Path, config_path: &Path) -> Result<(), FieldError> {
        let json = serde_json::to_vec_pretty(self.config()).map_err(|source| FieldError::Json {
            path: config_path.to_path_buf(),
            source,
        })?;
        let bytes = self.to_safetensors_bytes().map_err(|e| match e {
            FieldError::Safetensors { message, .. } => FieldError::Safetensors {
                path: weights_path.to_path_buf(),
                message,
            },
            other => other,
        })?;
        write_atomic(weights_path, &bytes)?;
        write_atomic(config_path, &json)
    }

    /// Saves to `dir/field.safetensors` and `dir/field.json` (creating `dir`).
    pub fn save_dir(&self, dir: &Path) -> Result<(), FieldError> {
        fs::create_dir_all(dir).map_err(|source| FieldError::Io {
            path: dir.to_path_buf(),
            source,
        })?;
        self.save(&dir.join("field.safetensors"), &dir.join("field.json"))
    }

    /// Loads from `dir/field.safetensors` and `dir/field.json`.
    pub fn load_dir(dir: &Path) -> Result<Self, FieldError> {
        Self::load(&dir.join("field.safetensors"), &dir.join("field.json"))
    }

    /// Loads a config (JSON) and the weights (safetensors) it describes.
    pub fn load(weights_path: &Path, config_path: &Path) -> Result<Self, FieldError> {
        let json = fs::read(config_path).map_err(|source| FieldError::Io {
            path: config_path.to_path_buf(),
            source,
        })?;
        let config: FieldConfig =
            serde_json::from_slice(&json).map_err(|source| FieldError::Json {
                path: config_path.to_path_buf(),
                source,
            })?;
        Self::load_weights(config, weights_path)
    }

    /// Loads weights for a given config; any shape disagreement is an error.
    pub fn load_weights(config: FieldConfig, weights_path: &Path) -> Result<Self, FieldError> {
        config.validate()?;
        let bytes = fs::read(weights_path).map_err(|source| FieldError::Io {
            path: weights_path.to_path_buf(),
            source,
        })?;
        let st = SafeTensors::deserialize(&bytes).map_err(|e| FieldError::Safetensors {
            path: weights_path.to_path_buf(),
            message: e.to_string(),
        })?;
        Self::from_safetensors(config, &st, weights_path)
    }

    /// Every weight tensor with its name and shape (as [`NerfactoField::tensor_shapes`]), for
    /// containers that store more than the field (a model with its occupancy grid).
    pub fn named_tensors(&self) -> Vec<(String, Vec<usize>, &[f32])> {
        Self::tensor_shapes(self.config())
            .into_iter()
            .zip(self.tensors())
            .map(|((name, shape), (_, data))| (name, shape, data))
            .collect()
    }

    /// Builds the field for `config` from the tensors of a parsed safetensors container
    /// (`path` only labels errors); extra tensors are ignored, missing or misshapen ones are
    /// an error.
    pub fn from_safetensors(
        config: FieldConfig,
        st: &SafeTensors<'_>,
        path: &Path,
    ) -> Result<Self, FieldError> {
        config.validate()?;
        let weights_path = path;
        let mut vals: Vec<Vec<f32>> = Vec::new();
        for (name, shape) in Self::tensor_shapes(&config) {
            let t = st.tensor(&name).map_err(|_| FieldError::MissingTensor {
                name: name.clone(),
                path: weights_path.to_path_buf(),
            })?;
            if t.dtype() != Dtype::F32 || t.shape() != shape.as_slice() {
                return Err(FieldError::ShapeMismatch {
                    name,
                    expected: shape,
                    actual: t.shape().to_vec(),
                });
            }
            // The byte buffer may be unaligned for f32, so decode instead of casting in place.
            vals.push(
                t.data()
                    .chunks_exact(4)
                    .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                    .collect(),
            );
        }
        let mut it = vals.into_iter();
        let mut next = || it.next().unwrap_or_default();
        let table = next();
        let ci = config.colour_input_dim();
        let dims = [(32, 64), (64, 16), (ci, 64), (64, 64), (64, 3)];
        let mut layers: Vec<Linear> = dims
            .iter()
            .map(|&(i, o)| Linear {
                n_in: i,
                n_out: o,
                w: next(),
                b: next(),
            })
            .collect();
        let appearance = next();
        let levels = HashGrid::layout(
            config.log2_table_size,
            config.base_resolution,
            config.max_resolution,
        );
        let c2 = layers.pop().unwrap_or_else(Linear::empty);
        let c1 = layers.pop().unwrap_or_else(Linear::empty);
        let c0 = layers.pop().unwrap_or_else(Linear::empty);
        let g1 = layers.pop().unwrap_or_else(Linear::empty);
        let g0 = layers.pop().unwrap_or_else(Linear::empty);
        Ok(Self::from_parts(
            config,
            HashGrid::from_parts(levels, table),
            [g0, g1],
            [c0, c1, c2],
            appearance,
        ))
    }
}

impl Linear {
    fn empty() -> Self {
        Self {
            n_in: 0,
            n_out: 0,
            w: Vec::new(),
            b: Vec::new(),
        }
    }
}
