//! Files as every crate writes and finds them: outputs written under a temporary name and renamed into place
//! (a reader, or a run killed midway, never sees half a file), JSON written that way, the files under a
//! directory, and a file's blake3.

use std::io;
use std::path::{Path, PathBuf};

/// The temporary name an output is written under before the atomic rename: `NAME.tmp` beside it.
pub fn tmp_path(path: &Path) -> PathBuf {
    let mut name = path
        .file_name()
        .map(|n| n.to_os_string())
        .unwrap_or_default();
    name.push(".tmp");
    path.with_file_name(name)
}

/// Write `path` through `write` on its temporary name, then rename it into place.
pub fn write_atomic<E: From<io::Error>>(
    path: &Path,
    write: impl FnOnce(&Path) -> Result<(), E>,
) -> Result<(), E> {
    let tmp = tmp_path(path);
    write(&tmp)?;
    std::fs::rename(&tmp, path)?;
    Ok(())
}

/// Write text atomically: a temp name, then rename, so a reader never sees half a file.
pub fn write_text_atomic(path: &Path, text: &str) -> io::Result<()> {
    write_atomic(path, |tmp| std::fs::write(tmp, text))
}

/// Write JSON atomically (temp name, then rename), pretty-printed with a trailing newline.
pub fn write_json_atomic<T: serde::Serialize>(path: &Path, value: &T) -> io::Result<()> {
    let mut text = serde_json::to_string_pretty(value).map_err(io::Error::other)?;
    text.push('\n');
    write_text_atomic(path, &text)
}

/// Every file under `dir` (recursively) with its size, sorted by path; none when `dir` does not exist.
pub fn files_under(dir: &Path) -> anyhow::Result<Vec<(PathBuf, u64)>> {
    let (mut found, mut pending) = (Vec::new(), vec![dir.to_path_buf()]);
    while let Some(d) = pending.pop() {
        let entries = match std::fs::read_dir(&d) {
            Ok(entries) => entries,
            Err(e) if e.kind() == io::ErrorKind::NotFound => continue,
            Err(e) => return Err(anyhow::Error::new(e).context(format!("listing {}", d.display()))),
        };
        for entry in entries {
            let entry = entry?;
            let meta = entry.metadata()?;
            if meta.is_dir() {
                pending.push(entry.path());
            } else {
                found.push((entry.path(), meta.len()));
            }
        }
    }
    found.sort();
    Ok(found)
}

/// blake3 of a file's bytes, hex.
pub fn hash_file(path: &Path) -> io::Result<String> {
    use std::io::Read;
    let mut hasher = blake3::Hasher::new();
    // 16 MiB reads hashed across the rayon pool: stage outputs run to gigabytes. (Not mmap: mapped pages
    // count as resident and would swamp the pipeline's peak-RSS figure.)
    let mut file = std::fs::File::open(path)?;
    let mut buffer = vec![0u8; 16 << 20];
    loop {
        let read = file.read(&mut buffer)?;
        if read == 0 {
            break;
        }
        hasher.update_rayon(&buffer[..read]);
    }
    Ok(hasher.finalize().to_hex().to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_atomic_write_leaves_the_file_and_no_temporary_one() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.json");
        write_json_atomic(&path, &serde_json::json!({"k": 1})).unwrap();
        assert_eq!(
            std::fs::read_to_string(&path).unwrap(),
            "{\n  \"k\": 1\n}\n"
        );
        assert!(!tmp_path(&path).exists());
        // A write that fails leaves no finished-looking file.
        let failed = write_atomic(&dir.path().join("b.txt"), |tmp| {
            std::fs::write(tmp, "half")?;
            Err(io::Error::other("killed"))
        });
        assert!(failed.is_err() && !dir.path().join("b.txt").exists());
        let listed = files_under(dir.path()).unwrap();
        let names: Vec<_> = listed
            .iter()
            .map(|(p, _)| p.file_name().unwrap().to_owned())
            .collect();
        assert_eq!(names, ["a.json", "b.txt.tmp"]);
        assert!(files_under(&dir.path().join("none")).unwrap().is_empty());
        // blake3 of "abc", the reference vector.
        std::fs::write(dir.path().join("abc"), "abc").unwrap();
        assert_eq!(
            hash_file(&dir.path().join("abc")).unwrap(),
            "6437b3ac38465133ffb63b75273a8db548c558465d79db03fd359c6cd5bd9d85"
        );
    }
}
