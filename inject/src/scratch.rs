//! A run's scratch folder: the temporary folder that holds one run's files (bootstrap's
//! events, state, stdout and stderr, the task's verdict) while the campaign reads them, and a
//! note in the campaign's output folder that names it for as long as it exists.
//!
//! The folder is removed when the run is done. A campaign killed outright (SIGKILL, a batch
//! system's hard time limit) cannot remove it, so the next campaign started on the same output
//! folder (`--resume`, or a classification resumed) removes what the notes name: a folder is
//! left behind at most until then, and never by a campaign that ends by itself or by SIGTERM.

use std::path::{Path, PathBuf};

/// The notes' names: `running-<folder name>` in the output folder, holding the folder's path
/// and the campaign's pid, one per line.
const NOTE_PREFIX: &str = "running-";
/// Every scratch folder's name starts with this: a note naming anything else is not obeyed.
const FOLDER_PREFIX: &str = "s3res-";

/// A run's temporary folder (prefix `prefix`, in the system's temporary directory), named by a
/// note in `out` until it is dropped.
pub struct ScratchDir {
    /// Removed before the note (see `Drop`).
    dir: Option<tempfile::TempDir>,
    note: PathBuf,
}

impl ScratchDir {
    /// Creates the folder, then its note in `out` (a kill between the two, a few µs, leaves
    /// the folder unnamed; a note that cannot be written removes the folder and is an error).
    pub fn new(out: &Path, prefix: &str) -> std::io::Result<ScratchDir> {
        debug_assert!(prefix.starts_with(FOLDER_PREFIX));
        let dir = tempfile::Builder::new().prefix(prefix).tempdir()?;
        let name = dir.path().file_name().unwrap_or_default().to_string_lossy();
        let note = out.join(format!("{NOTE_PREFIX}{name}"));
        let text = format!("{}\n{}\n", dir.path().display(), std::process::id());
        std::fs::write(&note, text)?;
        Ok(ScratchDir {
            dir: Some(dir),
            note,
        })
    }

    pub fn path(&self) -> &Path {
        self.dir.as_ref().expect("held until drop").path()
    }
}

impl Drop for ScratchDir {
    fn drop(&mut self) {
        // The folder first: a note whose folder is gone is harmless, a folder without its note
        // would be left behind by a kill between the two.
        if let Some(dir) = self.dir.take() {
            let path = dir.path().to_path_buf();
            if let Err(e) = dir.close() {
                tracing::warn!(folder = %path.display(), "cannot remove a run's scratch folder: {e}");
            }
        }
        let _ = std::fs::remove_file(&self.note);
    }
}

/// What [`sweep`] did with one note.
#[derive(Debug, PartialEq, Eq)]
pub enum Swept {
    /// The folder of a campaign no longer running was removed (or was gone already).
    Removed(PathBuf),
    /// The note's campaign is still running: left alone.
    InUse(PathBuf, i32),
    /// The note names no scratch folder of a run (not absolute, not `s3res-…`, not the note's
    /// own name, or a symbolic link): the note is removed, nothing else.
    Ignored(PathBuf),
}

/// Removes the scratch folders that the notes in `out` name and whose campaign is no longer
/// running, and those notes. A missing `out` has none.
pub fn sweep(out: &Path) -> Vec<Swept> {
    let Ok(entries) = std::fs::read_dir(out) else {
        return Vec::new();
    };
    let mut swept = Vec::new();
    for entry in entries.flatten() {
        let file_name = entry.file_name();
        let Some(folder_name) = file_name.to_str().and_then(|n| n.strip_prefix(NOTE_PREFIX)) else {
            continue;
        };
        let note = entry.path();
        let Ok(text) = std::fs::read_to_string(&note) else {
            continue;
        };
        let mut lines = text.lines();
        let folder = PathBuf::from(lines.next().unwrap_or_default());
        let pid = lines.next().and_then(|p| p.trim().parse::<i32>().ok());
        if let Some(pid) = pid.filter(|&p| campaign_alive(p)) {
            swept.push(Swept::InUse(folder, pid));
            continue;
        }
        let is_scratch = folder.is_absolute()
            && folder.file_name().and_then(|n| n.to_str()) == Some(folder_name)
            && folder_name.starts_with(FOLDER_PREFIX);
        // `symlink_metadata`: a link is never followed into somebody else's folder.
        let is_dir = std::fs::symlink_metadata(&folder).map(|m| m.is_dir());
        match (is_scratch, is_dir) {
            (true, Ok(true)) => match std::fs::remove_dir_all(&folder) {
                Ok(()) => swept.push(Swept::Removed(folder)),
                Err(e) => {
                    tracing::warn!(folder = %folder.display(), "cannot remove the scratch folder of a killed run: {e}");
                    continue; // the note stays: a later start tries again
                }
            },
            (true, Err(e)) if e.kind() == std::io::ErrorKind::NotFound => {
                swept.push(Swept::Removed(folder));
            }
            _ => swept.push(Swept::Ignored(folder)),
        }
        let _ = std::fs::remove_file(&note);
    }
    swept
}

/// Whether `pid` is a running `s3res-inject` (a pid taken over by another program is not).
fn campaign_alive(pid: i32) -> bool {
    std::fs::read_to_string(format!("/proc/{pid}/comm"))
        .is_ok_and(|comm| comm.trim_end() == "s3res-inject")
        && replica_rt::sys::process_state(pid).is_some_and(|s| s != 'Z')
}

/// Sweeps `out` (see [`sweep`]) and logs what it removed. An error if another `s3res-inject`
/// is running in `out`: two campaigns writing one folder would corrupt it.
pub fn sweep_and_report(out: &Path) -> anyhow::Result<()> {
    let mut busy = None;
    for s in sweep(out) {
        match s {
            Swept::Removed(folder) => tracing::info!(
                folder = %folder.display(),
                "removed the scratch folder of a run whose campaign was killed"
            ),
            Swept::InUse(_, pid) => busy = Some(pid),
            Swept::Ignored(folder) => tracing::warn!(
                folder = %folder.display(),
                "a note in the output folder names no scratch folder of a run; removed the note only"
            ),
        }
    }
    if let Some(pid) = busy {
        anyhow::bail!(
            "another s3res-inject (pid {pid}) is running in {}; wait for it to finish, or give \
             another --out folder",
            out.display()
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn note(out: &Path, folder: &Path, pid: i32) -> PathBuf {
        let name = folder.file_name().unwrap().to_string_lossy();
        let note = out.join(format!("{NOTE_PREFIX}{name}"));
        std::fs::write(&note, format!("{}\n{pid}\n", folder.display())).unwrap();
        note
    }

    /// A pid that no process has (the kernel's limit is below it).
    const NO_PID: i32 = i32::MAX;

    #[test]
    fn a_scratch_folder_is_named_while_it_exists_and_removed_with_its_note() {
        let out = tempfile::tempdir().unwrap();
        let scratch = ScratchDir::new(out.path(), "s3res-test-").unwrap();
        let path = scratch.path().to_path_buf();
        std::fs::write(path.join("stderr"), "x").unwrap();
        let notes: Vec<_> = std::fs::read_dir(out.path()).unwrap().flatten().collect();
        assert_eq!(notes.len(), 1);
        let text = std::fs::read_to_string(notes[0].path()).unwrap();
        assert_eq!(
            text,
            format!("{}\n{}\n", path.display(), std::process::id())
        );
        drop(scratch);
        assert!(!path.exists());
        assert_eq!(std::fs::read_dir(out.path()).unwrap().count(), 0);
    }

    #[test]
    fn a_killed_campaigns_folder_is_removed_and_only_that() {
        let out = tempfile::tempdir().unwrap();
        let tmp = tempfile::tempdir().unwrap();
        // Left behind by a killed campaign.
        let left = tmp.path().join("s3res-inject-AbC123");
        std::fs::create_dir_all(left.join("sub")).unwrap();
        std::fs::write(left.join("sub/events.jsonl"), "{}").unwrap();
        note(out.path(), &left, NO_PID);
        // Notes that must not be obeyed: a folder not named as a scratch folder, a name that
        // is not the note's, a relative path, and a link to a folder.
        let precious = tmp.path().join("precious");
        std::fs::create_dir(&precious).unwrap();
        note(out.path(), &precious, NO_PID);
        let other = tmp.path().join("s3res-inject-Other1");
        std::fs::create_dir(&other).unwrap();
        std::fs::write(
            out.path().join("running-s3res-inject-Xyz999"),
            format!("{}\n{NO_PID}\n", other.display()),
        )
        .unwrap();
        std::fs::write(
            out.path().join("running-s3res-inject-Rel000"),
            "s3res-inject-Rel000\n1\n",
        )
        .unwrap();
        let link = tmp.path().join("s3res-inject-Link00");
        std::os::unix::fs::symlink(&precious, &link).unwrap();
        note(out.path(), &link, NO_PID);
        // A note whose folder is gone already.
        note(out.path(), &tmp.path().join("s3res-inject-Gone00"), NO_PID);
        // A campaign's own files are not notes.
        std::fs::write(out.path().join("runs.jsonl"), "").unwrap();

        let mut swept = sweep(out.path());
        swept.sort_by_key(|s| format!("{s:?}"));
        assert_eq!(swept.len(), 6, "{swept:?}");
        assert!(swept.contains(&Swept::Removed(left.clone())), "{swept:?}");
        assert!(swept.contains(&Swept::Removed(tmp.path().join("s3res-inject-Gone00"))));
        assert!(swept.contains(&Swept::Ignored(precious.clone())));
        assert!(swept.contains(&Swept::Ignored(other.clone())));
        assert!(swept.contains(&Swept::Ignored(link.clone())));
        assert!(!left.exists());
        assert!(precious.is_dir() && other.is_dir() && link.exists());
        let rest: Vec<_> = std::fs::read_dir(out.path())
            .unwrap()
            .flatten()
            .map(|e| e.file_name())
            .collect();
        assert_eq!(rest, ["runs.jsonl"], "every note is gone");
    }

    #[test]
    fn the_folder_of_a_campaign_still_running_is_left_alone() {
        let out = tempfile::tempdir().unwrap();
        let tmp = tempfile::tempdir().unwrap();
        let busy = tmp.path().join("s3res-inject-Busy00");
        std::fs::create_dir(&busy).unwrap();
        // A live process of another name (this test) is not a campaign.
        let mine = std::process::id() as i32;
        assert!(!campaign_alive(mine));
        note(out.path(), &busy, mine);
        assert_eq!(sweep(out.path()), [Swept::Removed(busy.clone())]);

        // A process called s3res-inject is (`sleep` under that name, killed on drop).
        std::fs::create_dir(&busy).unwrap();
        let fake = tmp.path().join("s3res-inject");
        std::fs::copy("/bin/sleep", &fake).unwrap();
        struct Kill(std::process::Child);
        impl Drop for Kill {
            fn drop(&mut self) {
                let _ = self.0.kill();
                let _ = self.0.wait();
            }
        }
        let mut running = Kill(std::process::Command::new(&fake).arg("30").spawn().unwrap());
        let pid = running.0.id() as i32;
        let start = std::time::Instant::now();
        while !campaign_alive(pid) {
            assert!(
                start.elapsed() < std::time::Duration::from_secs(10),
                "{pid} never ran"
            );
            std::thread::sleep(std::time::Duration::from_millis(5));
        }
        note(out.path(), &busy, pid);
        assert_eq!(sweep(out.path()), [Swept::InUse(busy.clone(), pid)]);
        assert!(busy.is_dir());
        running.0.kill().unwrap();
        running.0.wait().unwrap();
        assert!(!campaign_alive(pid));
        assert_eq!(sweep(out.path()), [Swept::Removed(busy.clone())]);
        assert!(!busy.exists());
        assert!(sweep(&out.path().join("missing")).is_empty());
    }
}
