//! The test maps' NeRF: the production architecture with a smaller hash table, batch and
//! march (as the renderer's own tests), so a test map trains in seconds.

/// `nerf.model_overrides` of the test maps.
pub fn small_nerf_overrides() -> serde_json::Value {
    serde_json::json!({
        "field": {"log2_table_size": 15, "max_resolution": 512},
        "train": {"batch_rays": 1024, "march": {"steps": 128, "max_samples": 24},
                  "occupancy_warmup_steps": 32},
        "render": {"march": {"steps": 128}},
    })
}
