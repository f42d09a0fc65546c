//! The map directory: the versioned manifest with checksums ([`manifest`]), where each stage's
//! files live ([`layout`]), a built map loaded behind the stage traits ([`load`]), and the
//! content of its files checked beyond their checksums ([`check`]).

pub mod check;
pub mod layout;
pub mod load;
pub mod manifest;

pub use load::{LoadedBlocks, LoadedMap, MapBlock};
pub use manifest::{
    BlockEntry, BlockRecord, FileEntry, MANIFEST_VERSION, Manifest, MapDir, MapError, StageRecord,
    VirtualViewsRecord,
};
