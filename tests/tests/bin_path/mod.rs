//! Where the `matloc` binary of this build is, for the tests that run it as a user would.

use std::path::PathBuf;

/// `MATLOC_BIN`, else the `matloc` binary next to this test's target directory
/// (`target/<profile>/deps/<test>-<hash>` → `target/<profile>/matloc`). Fails the test with
/// how to build it when it is missing.
pub fn matloc_bin() -> PathBuf {
    if let Some(p) = std::env::var_os("MATLOC_BIN") {
        return PathBuf::from(p);
    }
    let exe = std::env::current_exe().expect("test executable path");
    let bin = exe
        .parent()
        .and_then(|d| d.parent())
        .map(|d| d.join("matloc"))
        .expect("target directory");
    assert!(
        bin.is_file(),
        "{} is missing: build it with `cargo build -p matloc-cli` (or set MATLOC_BIN)",
        bin.display()
    );
    bin
}
