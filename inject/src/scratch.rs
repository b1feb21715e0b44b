//! A run's scratch folder: the temporary folder that holds one run's files (bootstrap's
//! events, state, stdout and stderr, the task's verdict) while the campaign reads them, and a
//! note in the campaign's output folder that names it for as long as it exists.
//!
//! The folder is removed when the run is done. A campaign killed outright (SIGKILL, a batch
//! system's hard time limit, the OOM killer) cannot remove it, so the next campaign or
//! classification started on the same output folder (`--resume`) removes what the notes name:
//! a folder is left behind at most until then, and never by a campaign that ends by itself or
//! by SIGTERM.
//!
//! **Who is still running** is the kernel's to say, not a pid's: a campaign or classification
//! holds an exclusive lock (`flock`) on `OUT/.s3res-inject.lock` for as long as it runs
//! ([`OutLock`]), and the kernel lets go of it when the process dies, however it dies. So a
//! start that takes the lock knows that every note in the folder is a dead run's (a pid
//! would not: in a container a restarted campaign has the pid of the killed one), and a start
//! that cannot take it stops: two campaigns writing one folder would mix their records. On a
//! file system that takes no lock, a campaign says so and runs without the lock or the sweep.

use std::fs::{File, OpenOptions, TryLockError};
use std::io::{Read, Seek, Write};
use std::path::{Path, PathBuf};

use anyhow::Context;

/// The notes' names: `running-<folder name>` in the output folder, holding the folder's
/// absolute path and the campaign's pid, one per line.
const NOTE_PREFIX: &str = "running-";
/// The lock file in the output folder (left there: removing a lock file races with the next
/// process that opens it).
pub const LOCK_FILE: &str = ".s3res-inject.lock";
/// The scratch folders' names start with one of these: a note naming anything else is not
/// obeyed.
const FOLDER_PREFIXES: [&str; 3] = ["s3res-inject-", "s3res-classify-", "s3res-golden-"];

/// The exclusive lock of a running campaign or classification on its output folder: held
/// until dropped, or until the process dies.
#[derive(Debug)]
pub struct OutLock {
    _file: File,
}

/// Why [`OutLock::take`] took no lock.
#[derive(Debug, thiserror::Error)]
pub enum LockRefused {
    /// Another process holds it.
    #[error(
        "another s3res-inject{holder} is running a campaign or classification in {out}; wait for \
         it to finish, or give another --out folder"
    )]
    Busy { holder: String, out: String },
    /// The lock file cannot be opened (a folder that cannot be written).
    #[error("cannot open the lock file {path}: {source}")]
    Open {
        path: String,
        source: std::io::Error,
    },
    /// The file system takes no lock (`flock`): some network file systems.
    #[error("cannot lock {path}: {source}")]
    Unsupported {
        path: String,
        source: std::io::Error,
    },
}

impl OutLock {
    /// Takes the lock on `out` (which must exist), or says which process holds it.
    pub fn take(out: &Path) -> Result<OutLock, LockRefused> {
        let path = out.join(LOCK_FILE);
        let mut file = OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .map_err(|source| LockRefused::Open {
                path: path.display().to_string(),
                source,
            })?;
        match file.try_lock() {
            Ok(()) => {}
            Err(TryLockError::WouldBlock) => {
                // The holder's pid, as it wrote it when it took the lock (for the message
                // only: the lock alone says the folder is in use).
                let mut text = String::new();
                let _ = file.read_to_string(&mut text);
                let holder = match text.trim().parse::<u32>() {
                    Ok(pid) => format!(" (pid {pid})"),
                    Err(_) => String::new(),
                };
                return Err(LockRefused::Busy {
                    holder,
                    out: out.display().to_string(),
                });
            }
            Err(TryLockError::Error(source)) => {
                return Err(LockRefused::Unsupported {
                    path: path.display().to_string(),
                    source,
                });
            }
        }
        // Ours now: say who holds it.
        let said = file
            .set_len(0)
            .and_then(|()| file.rewind())
            .and_then(|()| writeln!(file, "{}", std::process::id()));
        if let Err(e) = said {
            tracing::warn!(file = %path.display(), "cannot write this process's pid into the lock file: {e}");
        }
        Ok(OutLock { _file: file })
    }
}

/// A run's temporary folder (prefix `prefix`, one of [`FOLDER_PREFIXES`], in the system's
/// temporary directory), named by a note in `out` until it is dropped. Made only under the
/// folder's [`OutLock`].
pub struct ScratchDir {
    /// Removed before the note (see `Drop`).
    dir: Option<tempfile::TempDir>,
    note: PathBuf,
}

impl ScratchDir {
    /// Creates the folder, then its note in `out` (a kill between the two, a few µs, leaves
    /// the folder unnamed; a note that cannot be written removes the folder and is an error).
    pub fn new(out: &Path, prefix: &str) -> anyhow::Result<ScratchDir> {
        debug_assert!(FOLDER_PREFIXES.contains(&prefix));
        // Absolute, also where TMPDIR is relative: the note must name it from anywhere.
        let tmp = std::path::absolute(std::env::temp_dir())
            .context("cannot tell where the temporary directory is")?;
        let dir = tempfile::Builder::new()
            .prefix(prefix)
            .tempdir_in(&tmp)
            .with_context(|| {
                format!(
                    "cannot create a temporary folder for a run in {}",
                    tmp.display()
                )
            })?;
        let name = dir.path().file_name().unwrap_or_default().to_string_lossy();
        let note = out.join(format!("{NOTE_PREFIX}{name}"));
        // Written under another name and renamed: a note is whole or absent.
        let part = out.join(format!(".{NOTE_PREFIX}{name}.part"));
        let text = format!("{}\n{}\n", dir.path().display(), std::process::id());
        std::fs::write(&part, text)
            .and_then(|()| std::fs::rename(&part, &note))
            .with_context(|| format!("cannot write {}", note.display()))?;
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
        // would be left behind by a kill between the two. A folder that cannot be removed keeps
        // its note, so that the next start tries again.
        if let Some(dir) = self.dir.take() {
            let path = dir.path().to_path_buf();
            if let Err(e) = dir.close() {
                tracing::warn!(folder = %path.display(), "cannot remove a run's scratch folder: {e}");
                return;
            }
        }
        if let Err(e) = std::fs::remove_file(&self.note) {
            tracing::warn!(note = %self.note.display(), "cannot remove a run's note: {e}");
        }
    }
}

/// What [`sweep`] did with one note.
#[derive(Debug, PartialEq, Eq)]
pub enum Swept {
    /// The folder of a killed campaign's run was removed, and the note.
    Removed(PathBuf),
    /// The folder was gone already: the note was removed.
    Gone(PathBuf),
    /// The note names no scratch folder of a run in `tmp` (not absolute, not named as one,
    /// not the note's own name, in another folder, or a symbolic link): the note is removed,
    /// nothing else.
    Ignored(PathBuf),
    /// The folder, or the note, could not be removed (the reason is logged): what could not
    /// stays, for a later start to try again.
    Failed(PathBuf),
}

/// Removes the scratch folders in `tmp` that the notes in `out` name, and those notes. Only
/// under `out`'s [`OutLock`]: every note is then a dead campaign's. A missing `out` has none.
pub fn sweep(out: &Path, tmp: &Path) -> Vec<Swept> {
    let entries = match std::fs::read_dir(out) {
        Ok(entries) => entries,
        Err(e) => {
            if e.kind() != std::io::ErrorKind::NotFound {
                tracing::warn!(folder = %out.display(), "cannot look for the notes of killed runs: {e}");
            }
            return Vec::new();
        }
    };
    let tmp = tmp.canonicalize().unwrap_or_else(|_| tmp.to_path_buf());
    let mut swept = Vec::new();
    for entry in entries.flatten() {
        let file_name = entry.file_name();
        let Some(file_name) = file_name.to_str() else {
            continue;
        };
        let note = entry.path();
        // A note a kill cut off before its rename names nothing for sure: it goes.
        if file_name.starts_with(&format!(".{NOTE_PREFIX}")) && file_name.ends_with(".part") {
            if let Err(e) = std::fs::remove_file(&note) {
                tracing::warn!(note = %note.display(), "cannot remove a note cut off by a kill: {e}");
            }
            continue;
        }
        let Some(folder_name) = file_name.strip_prefix(NOTE_PREFIX) else {
            continue;
        };
        let text = match std::fs::read_to_string(&note) {
            Ok(text) => text,
            Err(e) => {
                tracing::warn!(note = %note.display(), "cannot read the note of a killed run: {e}");
                continue;
            }
        };
        let folder = PathBuf::from(text.lines().next().unwrap_or_default());
        let in_tmp = folder
            .parent()
            .and_then(|p| p.canonicalize().ok())
            .is_some_and(|p| p == tmp);
        let is_scratch = folder.is_absolute()
            && in_tmp
            && folder.file_name().and_then(|n| n.to_str()) == Some(folder_name)
            && FOLDER_PREFIXES.iter().any(|p| folder_name.starts_with(p));
        // `symlink_metadata`: a link is never followed into somebody else's folder.
        let outcome = match std::fs::symlink_metadata(&folder).map(|m| m.is_dir()) {
            Ok(true) if is_scratch => match std::fs::remove_dir_all(&folder) {
                Ok(()) => Swept::Removed(folder),
                Err(e) => {
                    tracing::warn!(folder = %folder.display(), "cannot remove the scratch folder of a killed run: {e}");
                    swept.push(Swept::Failed(folder));
                    continue;
                }
            },
            Err(e) if e.kind() == std::io::ErrorKind::NotFound && is_scratch => Swept::Gone(folder),
            _ => Swept::Ignored(folder),
        };
        match std::fs::remove_file(&note) {
            Ok(()) => swept.push(outcome),
            Err(e) => {
                tracing::warn!(note = %note.display(), "cannot remove the note of a killed run: {e}");
                swept.push(Swept::Failed(note));
            }
        }
    }
    swept
}

/// Takes `out`'s lock (an error if another campaign or classification holds it), then sweeps
/// `out` (see [`sweep`]) and logs what it removed. The lock is to be held until the campaign
/// ends. On a file system that takes no lock this says so and goes on without one, and
/// without the sweep (which only the lock makes safe): `None`.
pub fn lock_and_sweep(out: &Path) -> anyhow::Result<Option<OutLock>> {
    let lock = match OutLock::take(out) {
        Ok(lock) => lock,
        Err(e @ LockRefused::Unsupported { .. }) => {
            tracing::warn!(
                "{e}: a second campaign started on this folder would not be stopped, and the \
                 temporary folders of killed runs are not removed"
            );
            return Ok(None);
        }
        Err(e) => return Err(e.into()),
    };
    for s in sweep(out, &std::env::temp_dir()) {
        match s {
            Swept::Removed(folder) => tracing::info!(
                folder = %folder.display(),
                "removed the scratch folder of a run whose campaign was killed"
            ),
            Swept::Gone(folder) => tracing::debug!(
                folder = %folder.display(),
                "the scratch folder of a run whose campaign was killed is gone already"
            ),
            Swept::Ignored(folder) => tracing::warn!(
                folder = %folder.display(),
                "a note in the output folder names no scratch folder of a run in this run's \
                 temporary directory; removed the note only"
            ),
            // Said as it happened.
            Swept::Failed(_) => {}
        }
    }
    Ok(Some(lock))
}

/// What an output folder (`--out`) is to hold.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OutKind {
    Campaign,
    Classification,
    /// What `merge` writes: a campaign's files or a classification's, into a new folder.
    Merge,
}

impl OutKind {
    fn name(self) -> &'static str {
        match self {
            OutKind::Campaign => "campaign",
            OutKind::Classification => "classification",
            OutKind::Merge => "merge",
        }
    }
}

/// Why [`check_out`] refused an output folder.
#[derive(Debug, thiserror::Error)]
pub enum OutRefused {
    /// It holds the other experiment's files: writing both into one folder makes it neither
    /// (`merge` refuses it).
    #[error(
        "--out {out} holds {holds}; a {kind} needs a folder of its own: give a new or empty \
         --out folder"
    )]
    OtherKind {
        out: String,
        holds: String,
        kind: &'static str,
    },
    /// It holds files of no campaign or classification.
    #[error(
        "--out {out} is not empty (it holds {entry}) and holds no {kind}; give a new or empty \
         --out folder"
    )]
    NotEmpty {
        out: String,
        entry: String,
        kind: &'static str,
    },
    /// `merge` writes only into a new or empty folder.
    #[error(
        "merge --out {out} is not empty (it holds {holds}); merge writes only into a new or \
         empty folder: give another --out"
    )]
    MergeInto { out: String, holds: String },
    #[error("cannot read the output folder {out}: {source}")]
    Read { out: String, source: std::io::Error },
}

/// What `name` in an output folder is: a file of a campaign's, of a classification's (or one
/// of them cut short: `NAME.tmp`), or neither.
fn kind_of(name: &str) -> Option<OutKind> {
    let name = name.strip_suffix(".tmp").unwrap_or(name);
    if crate::campaign::OUTPUT_FILES.contains(&name) || name == "runs" {
        Some(OutKind::Campaign)
    } else if crate::classify::OUTPUT_FILES.contains(&name) {
        Some(OutKind::Classification)
    } else {
        None
    }
}

/// What a folder's `name` says it holds, for a refusal.
fn holding(name: &str) -> String {
    match kind_of(name) {
        Some(kind) => format!("a {} ({name})", kind.name()),
        None if name == LOCK_FILE => format!("the lock of a campaign or classification ({name})"),
        None if name.starts_with(NOTE_PREFIX) => format!("a killed run's note ({name})"),
        None => name.to_owned(),
    }
}

/// Checks `out` before a `kind` writes into it, as `--out` is documented: a new or empty folder,
/// or one that holds the same kind (which only `--resume` continues: the campaign or
/// classification then says whether it is the same one, and refuses it without `--resume`). A campaign's or classification's lock file and killed runs'
/// notes are not content (the start sweeps them); for `merge` they are (a campaign's folder).
pub fn check_out(out: &Path, kind: OutKind) -> Result<(), OutRefused> {
    let entries = match std::fs::read_dir(out) {
        Ok(entries) => entries,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
        Err(source) => {
            return Err(OutRefused::Read {
                out: out.display().to_string(),
                source,
            })
        }
    };
    let mut names: Vec<String> = entries
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    let out_s = out.display().to_string();
    if kind == OutKind::Merge {
        // The most telling entry: a campaign's or classification's file, else its lock, else any.
        let first = names
            .iter()
            .find(|n| kind_of(n).is_some())
            .or_else(|| names.iter().find(|n| *n == LOCK_FILE))
            .or(names.first());
        return match first {
            Some(n) => Err(OutRefused::MergeInto {
                out: out_s,
                holds: holding(n),
            }),
            None => Ok(()),
        };
    }
    let content: Vec<&String> = names
        .iter()
        .filter(|n| *n != LOCK_FILE && !n.starts_with(NOTE_PREFIX))
        .filter(|n| !(n.starts_with(&format!(".{NOTE_PREFIX}")) && n.ends_with(".part")))
        .collect();
    if let Some(n) = content
        .iter()
        .find(|n| kind_of(n).is_some_and(|k| k != kind))
    {
        return Err(OutRefused::OtherKind {
            out: out_s,
            holds: holding(n),
            kind: kind.name(),
        });
    }
    let own = content.iter().any(|n| kind_of(n) == Some(kind));
    match content.first() {
        Some(n) if !own => Err(OutRefused::NotEmpty {
            out: out_s,
            entry: holding(n),
            kind: kind.name(),
        }),
        // The same kind: resumed (`--resume`), else refused by the campaign or classification
        // itself, which reads it.
        _ => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn note(out: &Path, folder: &Path) -> PathBuf {
        let name = folder.file_name().unwrap().to_string_lossy();
        let note = out.join(format!("{NOTE_PREFIX}{name}"));
        std::fs::write(&note, format!("{}\n1234\n", folder.display())).unwrap();
        note
    }

    #[test]
    fn a_scratch_folder_is_named_while_it_exists_and_removed_with_its_note() {
        let out = tempfile::tempdir().unwrap();
        let scratch = ScratchDir::new(out.path(), "s3res-inject-").unwrap();
        let path = scratch.path().to_path_buf();
        assert!(path.is_absolute());
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
        note(out.path(), &left);
        // Notes that must not be obeyed: a folder not named as a scratch folder, one of
        // s3res's but not a run's, a name that is not the note's, a relative path, a link to
        // a folder, and a scratch folder's name in another folder than the temporary one.
        let precious = tmp.path().join("precious");
        std::fs::create_dir(&precious).unwrap();
        note(out.path(), &precious);
        let runtime = tmp.path().join("s3res-runtime-Run000");
        std::fs::create_dir(&runtime).unwrap();
        note(out.path(), &runtime);
        let other = tmp.path().join("s3res-inject-Other1");
        std::fs::create_dir(&other).unwrap();
        std::fs::write(
            out.path().join("running-s3res-inject-Xyz999"),
            format!("{}\n", other.display()),
        )
        .unwrap();
        std::fs::write(
            out.path().join("running-s3res-inject-Rel000"),
            "s3res-inject-Rel000\n1\n",
        )
        .unwrap();
        let link = tmp.path().join("s3res-inject-Link00");
        std::os::unix::fs::symlink(&precious, &link).unwrap();
        note(out.path(), &link);
        let elsewhere = precious.join("s3res-golden-Away00");
        std::fs::create_dir(&elsewhere).unwrap();
        note(out.path(), &elsewhere);
        // A note whose folder is gone already, and one a kill cut off before its rename.
        let gone = tmp.path().join("s3res-classify-Gone00");
        note(out.path(), &gone);
        std::fs::write(out.path().join(".running-s3res-inject-Cut000.part"), "/tm").unwrap();
        // A campaign's own files are not notes.
        std::fs::write(out.path().join("runs.jsonl"), "").unwrap();

        let mut swept = sweep(out.path(), tmp.path());
        swept.sort_by_key(|s| format!("{s:?}"));
        assert_eq!(swept.len(), 8, "{swept:?}");
        assert!(swept.contains(&Swept::Removed(left.clone())), "{swept:?}");
        assert!(swept.contains(&Swept::Gone(gone)), "{swept:?}");
        for ignored in [&precious, &runtime, &other, &link, &elsewhere] {
            assert!(
                swept.contains(&Swept::Ignored(ignored.clone())),
                "{swept:?}"
            );
        }
        assert!(!left.exists());
        assert!(precious.is_dir() && runtime.is_dir() && other.is_dir() && elsewhere.is_dir());
        assert!(link.exists());
        let rest: Vec<_> = std::fs::read_dir(out.path())
            .unwrap()
            .flatten()
            .map(|e| e.file_name())
            .collect();
        assert_eq!(rest, ["runs.jsonl"], "every note is gone");
        assert!(sweep(&out.path().join("missing"), tmp.path()).is_empty());
    }

    #[test]
    fn a_folder_in_use_is_refused_to_a_second_start_until_its_lock_is_let_go() {
        let out = tempfile::tempdir().unwrap();
        let tmp = tempfile::tempdir().unwrap();
        let first = OutLock::take(out.path()).unwrap();
        // A lock is per open file: a second start in this same process is refused too.
        let refused = OutLock::take(out.path()).unwrap_err().to_string();
        assert_eq!(
            refused,
            format!(
                "another s3res-inject (pid {}) is running a campaign or classification in {}; \
                 wait for it to finish, or give another --out folder",
                std::process::id(),
                out.path().display()
            )
        );
        // The holder's notes are not swept by a start that was refused...
        let busy = tmp.path().join("s3res-inject-Busy00");
        std::fs::create_dir(&busy).unwrap();
        note(out.path(), &busy);
        assert!(lock_and_sweep(out.path()).is_err());
        assert!(busy.is_dir());
        // ...and are, by the next start once it is gone (a killed holder's lock goes with
        // its process: the campaign_stop test kills one).
        drop(first);
        let again = OutLock::take(out.path()).unwrap();
        assert_eq!(
            sweep(out.path(), tmp.path()),
            [Swept::Removed(busy.clone())]
        );
        assert!(!busy.exists());
        drop(again);
        let rest: Vec<_> = std::fs::read_dir(out.path())
            .unwrap()
            .flatten()
            .map(|e| e.file_name())
            .collect();
        assert_eq!(rest, [LOCK_FILE], "the lock file stays, nothing else");
    }
}
