//! The map directory: the versioned manifest with checksums ([`manifest`]), where each stage's
//! files live ([`layout`]), and a built map loaded behind the stage traits ([`load`]).

pub mod layout;
pub mod load;
pub mod manifest;

pub use load::{LoadedBlocks, LoadedMap, MapBlock};
pub use manifest::{
    BlockEntry, BlockRecord, FileEntry, MANIFEST_VERSION, Manifest, MapDir, MapError, StageRecord,
};
