use crate::error::RenderError;

/// A batch of rays in world coordinates (metres).
///
/// Directions must be unit length: depths are reported as distances along the ray, which
/// equal the ray parameter `t` only for unit directions.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RayBatch {
    /// Ray origins (camera centres), world frame.
    pub origins: Vec<[f32; 3]>,
    /// Unit directions, world frame.
    pub directions: Vec<[f32; 3]>,
    /// Start of the sampled range (metres along the ray).
    pub near: Vec<f32>,
    /// End of the sampled range.
    pub far: Vec<f32>,
    /// Image (appearance) index per ray; `None` uses the field's fallback embedding.
    pub appearance: Option<Vec<u32>>,
}

impl RayBatch {
    /// Rays sharing one `near`/`far` range and no appearance index; checks them.
    pub fn new(
        origins: Vec<[f32; 3]>,
        directions: Vec<[f32; 3]>,
        near: f32,
        far: f32,
    ) -> Result<Self, RenderError> {
        let n = origins.len();
        let b = Self {
            origins,
            directions,
            near: vec![near; n],
            far: vec![far; n],
            appearance: None,
        };
        b.validate()?;
        Ok(b)
    }

    /// Number of rays.
    pub fn len(&self) -> usize {
        self.origins.len()
    }

    /// Whether there are no rays.
    pub fn is_empty(&self) -> bool {
        self.origins.is_empty()
    }

    /// Checks lengths, finiteness, unit directions and `0 <= near < far`.
    pub fn validate(&self) -> Result<(), RenderError> {
        let n = self.origins.len();
        for (what, len) in [
            ("directions", self.directions.len()),
            ("near", self.near.len()),
            ("far", self.far.len()),
        ] {
            if len != n {
                return Err(RenderError::LengthMismatch {
                    what,
                    expected: n,
                    actual: len,
                });
            }
        }
        if let Some(a) = &self.appearance
            && a.len() != n
        {
            return Err(RenderError::LengthMismatch {
                what: "appearance",
                expected: n,
                actual: a.len(),
            });
        }
        for i in 0..n {
            let o = self.origins[i];
            let d = self.directions[i];
            if !o.iter().chain(d.iter()).all(|v| v.is_finite()) {
                return Err(RenderError::InvalidRay {
                    index: i,
                    reason: "non-finite origin or direction",
                });
            }
            let len2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
            if (len2 - 1.0).abs() > 1e-3 {
                return Err(RenderError::InvalidRay {
                    index: i,
                    reason: "direction is not unit length",
                });
            }
            let (nr, fr) = (self.near[i], self.far[i]);
            if !(nr.is_finite() && fr.is_finite() && nr >= 0.0 && fr > nr) {
                return Err(RenderError::InvalidRay {
                    index: i,
                    reason: "need finite 0 <= near < far",
                });
            }
        }
        Ok(())
    }

    /// The rays at `indices` (a training mini-batch).
    pub fn gather(&self, indices: &[usize]) -> Self {
        Self {
            origins: indices.iter().map(|&i| self.origins[i]).collect(),
            directions: indices.iter().map(|&i| self.directions[i]).collect(),
            near: indices.iter().map(|&i| self.near[i]).collect(),
            far: indices.iter().map(|&i| self.far[i]).collect(),
            appearance: self
                .appearance
                .as_ref()
                .map(|a| indices.iter().map(|&i| a[i]).collect()),
        }
    }

    /// Narrows every ray's `[near, far]` to where it crosses the box `[min, max]` (slab
    /// test). Rays that miss the box, or cross it only outside `[near, far]`, keep their
    /// range. Used for scenes whose content lies inside the box (aerial surveys): samples are
    /// then spent on the scene, not on the air above it or the contracted far field.
    pub fn clip_to_box(&mut self, min: [f32; 3], max: [f32; 3]) {
        for i in 0..self.len() {
            let (o, d) = (self.origins[i], self.directions[i]);
            let (mut t0, mut t1) = (f32::NEG_INFINITY, f32::INFINITY);
            for a in 0..3 {
                if d[a].abs() < 1e-12 {
                    if o[a] < min[a] || o[a] > max[a] {
                        t0 = f32::INFINITY;
                    }
                    continue;
                }
                let inv = 1.0 / d[a];
                let (u, v) = ((min[a] - o[a]) * inv, (max[a] - o[a]) * inv);
                t0 = t0.max(u.min(v));
                t1 = t1.min(u.max(v));
            }
            let near = self.near[i].max(t0);
            let far = self.far[i].min(t1);
            // A sliver shorter than a millimetre is not worth sampling; keep the full range.
            if far > near + 1e-3 {
                self.near[i] = near;
                self.far[i] = far;
            }
        }
    }

    /// Point at distance `t` along ray `i`.
    #[inline]
    pub fn at(&self, i: usize, t: f32) -> [f32; 3] {
        let o = self.origins[i];
        let d = self.directions[i];
        [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]]
    }
}

/// Samples of many rays as intervals `[t_start, t_end]`, ray `r` owning
/// `offsets[r]..offsets[r+1]`. Samples are evaluated at the interval midpoints.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RaySamples {
    /// Prefix offsets, `n_rays + 1` entries.
    pub offsets: Vec<usize>,
    /// Interval starts (metres along the ray).
    pub t_start: Vec<f32>,
    /// Interval ends.
    pub t_end: Vec<f32>,
}

impl RaySamples {
    /// Builds from per-ray interval lists.
    pub fn from_per_ray(per_ray: Vec<Vec<(f32, f32)>>) -> Self {
        let total: usize = per_ray.iter().map(Vec::len).sum();
        let mut s = Self {
            offsets: Vec::with_capacity(per_ray.len() + 1),
            t_start: Vec::with_capacity(total),
            t_end: Vec::with_capacity(total),
        };
        s.offsets.push(0);
        for r in per_ray {
            for (a, b) in r {
                s.t_start.push(a);
                s.t_end.push(b);
            }
            s.offsets.push(s.t_start.len());
        }
        s
    }

    /// Number of rays.
    pub fn num_rays(&self) -> usize {
        self.offsets.len().saturating_sub(1)
    }

    /// Total number of samples.
    pub fn len(&self) -> usize {
        self.t_start.len()
    }

    /// Whether there are no samples.
    pub fn is_empty(&self) -> bool {
        self.t_start.is_empty()
    }

    /// Sample range of ray `r`.
    #[inline]
    pub fn range(&self, r: usize) -> std::ops::Range<usize> {
        self.offsets[r]..self.offsets[r + 1]
    }

    /// Interval midpoint of sample `k`.
    #[inline]
    pub fn t_mid(&self, k: usize) -> f32 {
        0.5 * (self.t_start[k] + self.t_end[k])
    }

    /// World positions (midpoints), directions and appearance index of every sample.
    pub fn points(&self, rays: &RayBatch) -> (Vec<[f32; 3]>, Vec<[f32; 3]>, Vec<u32>) {
        let n = self.len();
        let mut pts = Vec::with_capacity(n);
        let mut dirs = Vec::with_capacity(n);
        let mut app = Vec::new();
        for r in 0..self.num_rays() {
            for k in self.range(r) {
                pts.push(rays.at(r, self.t_mid(k)));
                dirs.push(rays.directions[r]);
            }
            if let Some(a) = &rays.appearance {
                app.extend(std::iter::repeat_n(a[r], self.range(r).len()));
            }
        }
        (pts, dirs, app)
    }
}
