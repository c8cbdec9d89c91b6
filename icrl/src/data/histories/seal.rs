//! Integrity: the SHA-256 of a file's body in its HDF5 user block, written
//! last and checked before libhdf5 parses anything; and a merged file's
//! record of its shards, each checked the same way before a read goes
//! through to it.

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::{HistoryError, Problem};

/// Bytes of the user block that holds the file's checksum.
pub(crate) const USER_BLOCK: usize = 512;
/// How the checksum line in the user block starts.
pub(super) const CHECKSUM_TAG: &[u8] = b"icrl-histories sha256 ";

/// SHA-256 (hex) of the bytes of `path` after the user block.
fn body_sha256(path: &Path) -> std::io::Result<String> {
    use sha2::Digest;
    use std::io::{Read, Seek, SeekFrom};
    let mut f = std::fs::File::open(path)?;
    f.seek(SeekFrom::Start(USER_BLOCK as u64))?;
    let mut hasher = sha2::Sha256::new();
    let mut buf = vec![0u8; 1 << 16];
    loop {
        let n = f.read(&mut buf)?;
        if n == 0 {
            break;
        }
        hasher.update(&buf[..n]);
    }
    Ok(hasher
        .finalize()
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect())
}

/// Writes the checksum line into the user block of a finished file.
pub(crate) fn seal(path: &Path) -> std::io::Result<()> {
    use std::io::{Seek, SeekFrom, Write};
    let line = [CHECKSUM_TAG, body_sha256(path)?.as_bytes(), b"\n"].concat();
    let mut f = std::fs::OpenOptions::new().write(true).open(path)?;
    f.seek(SeekFrom::Start(0))?;
    f.write_all(&line)?;
    f.sync_all()
}

/// Refuses a path that is not a regular file before anything opens it:
/// opening a FIFO blocks until a writer comes, where no stop signal can end
/// the wait, and a device or a folder holds no histories.
fn regular_file(path: &Path) -> Result<(), Problem> {
    std::fs::metadata(path).map_err(|e| Problem::Unreadable(e.to_string()))?;
    crate::guard::regular_file(path)
        .map_err(|what| Problem::Unreadable(format!("{what}: give the dataset's .h5 file")))
}

/// Checks the checksum in the user block and returns it. `Ok(None)`: the
/// file has no checksum (written elsewhere); an error: the bytes do not match it.
pub(crate) fn verify_seal(path: &Path) -> Result<Option<String>, Problem> {
    use std::io::Read;
    regular_file(path)?;
    let mut head = vec![0u8; CHECKSUM_TAG.len() + 64];
    let mut f = std::fs::File::open(path).map_err(|e| Problem::Unreadable(e.to_string()))?;
    if f.read_exact(&mut head).is_err() || !head.starts_with(CHECKSUM_TAG) {
        return Ok(None);
    }
    let want = String::from_utf8_lossy(&head[CHECKSUM_TAG.len()..]).into_owned();
    let got = body_sha256(path).map_err(|e| Problem::Unreadable(e.to_string()))?;
    if got != want {
        return Err(Problem::Damaged(format!(
            "SHA-256 of its contents is {got}, the file records {want}: it was damaged or altered \
             after writing; make it again with `icrl dataset`"
        )));
    }
    Ok(Some(got))
}

/// Attribute of a merged file listing its shards.
pub(crate) const SHARDS_ATTR: &str = "shards";

/// One shard as a merged file records it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub(crate) struct ShardRecord {
    /// Path relative to the merged file's folder.
    pub(crate) file: String,
    /// The shard's SHA-256 (of the bytes after its user block) at merging.
    pub(crate) sha256: String,
}

/// For a merged file (one with a `shards` attribute): checks that every
/// shard is there, passes its own checksum, and is the file that was
/// merged (its SHA-256 is the recorded one). Other files pass unchecked.
pub(super) fn verify_shards(f: &hdf5::File, path: &Path) -> Result<(), HistoryError> {
    let Ok(attr) = f.attr(SHARDS_ATTR) else {
        return Ok(());
    };
    let damaged = |what: String| HistoryError::new(path, Problem::Damaged(what));
    let text = attr
        .read_scalar::<hdf5::types::VarLenUnicode>()
        .map_err(|e| damaged(format!("attribute {SHARDS_ATTR}: {e}")))?;
    let records: Vec<ShardRecord> = serde_json::from_str(text.as_str())
        .map_err(|e| damaged(format!("attribute {SHARDS_ATTR}: {e}")))?;
    let base = path.parent().unwrap_or(Path::new("."));
    for r in &records {
        let shard = base.join(&r.file);
        if !shard.is_file() {
            return Err(damaged(format!(
                "its shard {} is missing; keep the merged file and its shards together",
                shard.display()
            )));
        }
        let got = verify_seal(&shard)
            .map_err(|p| HistoryError::new(&shard, p))?
            .ok_or_else(|| damaged(format!("its shard {} has no checksum", shard.display())))?;
        if got != r.sha256 {
            return Err(damaged(format!(
                "its shard {} is not the file that was merged (SHA-256 {got}, merged {}): it was \
                 made again or replaced; merge again with `icrl dataset merge`",
                shard.display(),
                r.sha256
            )));
        }
    }
    Ok(())
}
