//! Files the tool writes for others to read (the shard map, the router's
//! configuration, the supervisor's state), each written whole.

use std::path::Path;

use anyhow::{Context, Result};

/// Writes a file through a temporary sibling and a rename, so a reader
/// never sees half of it.
pub(crate) fn write_atomic(path: &Path, text: &str) -> Result<()> {
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, text).with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, path).with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}
