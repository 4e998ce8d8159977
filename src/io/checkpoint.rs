//! Atomic checkpoint files: write to a temporary file beside the target, `fsync` it, rename
//! it over the target, `fsync` the directory. A reader sees either the old checkpoint or
//! the new one, never a torn file, whatever moment the process is killed at.

use std::fs::{self, File};
use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use serde::Serialize;
use serde::de::DeserializeOwned;

/// The temporary file a checkpoint is written to before the rename.
fn temporary(path: &Path) -> PathBuf {
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(".tmp");
    path.with_file_name(name)
}

/// Writes `value` to `path` atomically (module docs).
pub fn write_atomic<T: Serialize>(path: &Path, value: &T) -> Result<()> {
    let tmp = temporary(path);
    let bytes = crate::contract::to_wire(value);
    {
        let mut f = File::create(&tmp)
            .with_context(|| format!("cannot create checkpoint {}", tmp.display()))?;
        f.write_all(&bytes)
            .and_then(|()| f.sync_all())
            .with_context(|| format!("cannot write checkpoint {}", tmp.display()))?;
    }
    fs::rename(&tmp, path)
        .with_context(|| format!("cannot move {} to {}", tmp.display(), path.display()))?;
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    // Make the rename itself durable.
    File::open(dir)
        .and_then(|d| d.sync_all())
        .with_context(|| format!("cannot sync directory {}", dir.display()))?;
    Ok(())
}

/// Reads a checkpoint; `None` if there is none.
pub fn read<T: DeserializeOwned>(path: &Path) -> Result<Option<T>> {
    match fs::read(path) {
        Ok(bytes) => serde_json::from_slice(&bytes)
            .map(Some)
            .with_context(|| format!("checkpoint {} is not valid", path.display())),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(e).with_context(|| format!("cannot read checkpoint {}", path.display())),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_overwrite_leave_no_temporary() {
        let dir = std::env::temp_dir().join(format!("bw-ckpt-{}", std::process::id()));
        fs::create_dir_all(&dir).unwrap();
        let p = dir.join("state.json");
        assert!(read::<serde_json::Value>(&p).unwrap().is_none());
        write_atomic(&p, &serde_json::json!({"a": 1})).unwrap();
        write_atomic(&p, &serde_json::json!({"a": 2})).unwrap();
        assert_eq!(read::<serde_json::Value>(&p).unwrap().unwrap()["a"], 2);
        assert!(!temporary(&p).exists());
        fs::write(&p, b"{trunc").unwrap();
        let e = read::<serde_json::Value>(&p).unwrap_err();
        assert!(format!("{e:#}").contains("is not valid"), "{e:#}");
        fs::remove_dir_all(&dir).unwrap();
    }
}
