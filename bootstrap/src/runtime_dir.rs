//! bootstrap's runtime folder, `<tmp>/s3res-<pid>-<n>` (mode 0700): the voters' sockets, to
//! which replicas connect (a fork child's spare line, a replica rebinding to a new voter), and
//! the injector's live view. It must exist for as long as bootstrap runs, and a bootstrap that
//! dies without cleaning up (SIGKILL, a power cut) leaves it behind, for the next one to remove.
//!
//! **Who is still running** is the kernel's to say, not a pid's: a bootstrap holds an
//! exclusive lock (`flock`) on its folder for as long as it lives ([`RuntimeDir`]), and the
//! kernel lets go of it when bootstrap dies, however it dies. The next bootstrap removes only
//! folders whose lock it can take. Before the lock, a folder counted as dead when its pid was
//! not a process named `s3res-bootstrap`: so a bootstrap started under another name (a renamed
//! copy, a link) had its live folder removed by the next one — and one in another pid
//! namespace sharing `/tmp` would have — after which its replicas were no longer rebuilt by
//! fork (a fork child reaches its voter through the folder) but by exec, their state lost,
//! two seconds after their death. The name check stays as a second guard, for a folder of a
//! bootstrap too old to lock it (which it protects only under its own name, and not when it
//! has this bootstrap's pid in another pid namespace).
//!
//! On a file system that takes no lock, bootstrap says so once, runs without one, and removes
//! no other folder (it cannot tell a live one).

use std::fs::{File, TryLockError};
use std::os::unix::fs::{DirBuilderExt, MetadataExt};
use std::path::{Path, PathBuf};

/// The runtime folder of this bootstrap, locked while it is held (no lock on a file system
/// that takes none).
#[derive(Debug)]
pub struct RuntimeDir {
    path: PathBuf,
    _lock: Option<File>,
}

impl RuntimeDir {
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Removes the folder, then lets go of its lock (so no sweep meanwhile takes the name).
    pub fn remove(self) {
        if let Err(e) = std::fs::remove_dir_all(&self.path) {
            if e.kind() != std::io::ErrorKind::NotFound {
                tracing::warn!("cannot remove runtime folder {}: {e}", self.path.display());
            }
        }
    }
}

/// Candidate names tried (`s3res-<pid>-0` …) before giving up.
const CANDIDATES: u32 = 1000;

/// Makes and locks a new runtime folder in `tmp`, after removing the folders of dead
/// bootstraps there.
pub fn make(tmp: &Path) -> std::io::Result<RuntimeDir> {
    remove_stale(tmp);
    let pid = std::process::id();
    for n in 0..CANDIDATES {
        let path = tmp.join(format!("s3res-{pid}-{n}"));
        match std::fs::DirBuilder::new().mode(0o700).create(&path) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
            Err(e) => return Err(e),
        }
        let dir = match File::open(&path) {
            Ok(dir) => dir,
            // Another bootstrap's sweep took it between the two calls (see `remove_stale`).
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => continue,
            Err(e) => {
                let _ = std::fs::remove_dir(&path);
                return Err(e);
            }
        };
        // Still the folder made above? A sweep that held its lock a moment may have removed
        // it, and someone else made one by that name since.
        if !same_file(&dir, &path) {
            continue;
        }
        if let Err(e) = check_private(&dir) {
            let _ = std::fs::remove_dir(&path);
            return Err(e);
        }
        match dir.try_lock() {
            // From here on no sweep takes it; and still the folder made above.
            Ok(()) if same_file(&dir, &path) => {
                return Ok(RuntimeDir {
                    path,
                    _lock: Some(dir),
                })
            }
            Ok(()) => continue,
            // A sweep holds it for a moment: take the next name (the empty folder is removed
            // by a later sweep, once this bootstrap is gone).
            Err(TryLockError::WouldBlock) => continue,
            Err(TryLockError::Error(e)) => {
                tracing::warn!(
                    "cannot lock the runtime folder {} ({e}): the folders of bootstraps that \
                     were killed are not removed from {}; a TMPDIR on a local file system \
                     takes locks",
                    path.display(),
                    tmp.display()
                );
                return Ok(RuntimeDir { path, _lock: None });
            }
        }
    }
    Err(std::io::Error::new(
        std::io::ErrorKind::AlreadyExists,
        format!("{CANDIDATES} candidate names are taken"),
    ))
}

/// That `dir`, just made with mode 0700, is a directory of this user that no one else can
/// enter (a umask only takes bits away). A file system that keeps neither owners nor modes
/// (NFS squashing users, vfat) would hand the voters' sockets to whoever it says owns them.
fn check_private(dir: &File) -> std::io::Result<()> {
    let m = dir.metadata()?;
    let me = nix::unistd::geteuid().as_raw();
    if m.is_dir() && m.uid() == me && m.mode() & 0o077 == 0 {
        return Ok(());
    }
    Err(std::io::Error::other(format!(
        "a folder made there with mode 0700 by uid {me} is owned by uid {} with mode {:o}: \
         the file system keeps no owners or modes; set TMPDIR to a folder on a local file system",
        m.uid(),
        m.mode() & 0o7777
    )))
}

fn same_file(open: &File, path: &Path) -> bool {
    match (open.metadata(), std::fs::symlink_metadata(path)) {
        (Ok(a), Ok(b)) => a.dev() == b.dev() && a.ino() == b.ino(),
        _ => false,
    }
}

/// The pid in a runtime folder's name (`s3res-<pid>-<n>`), if it is one.
fn pid_of(name: &str) -> Option<libc::pid_t> {
    let (pid, n) = name.strip_prefix("s3res-")?.split_once('-')?;
    n.parse::<u32>().ok()?;
    pid.parse().ok()
}

/// Whether `pid` is another process named `s3res-bootstrap` (the kernel keeps 15 bytes of a
/// name). Not this one: a folder named with this bootstrap's own pid is a dead one's that had
/// it before (in a container, bootstrap is pid 1 at every start), as this one's are locked.
pub(crate) fn is_other_bootstrap(pid: libc::pid_t) -> bool {
    if u32::try_from(pid) == Ok(std::process::id()) {
        return false;
    }
    let comm = replica_rt::sys::command_name(pid).unwrap_or_default();
    matches!(comm.trim_end(), "s3res-bootstrap" | "s3res-bootstra")
}

/// Removes the runtime folders of dead bootstraps in `tmp`: ours (same user), named
/// `s3res-<pid>-<n>`, a directory, and unlocked.
fn remove_stale(tmp: &Path) {
    let Ok(entries) = std::fs::read_dir(tmp) else {
        return;
    };
    // The effective uid, not `/proc/self`'s owner: that is root for a bootstrap given
    // capabilities with `setcap` (docs/real-time.md), which the kernel makes non-dumpable.
    let me = nix::unistd::geteuid().as_raw();
    for entry in entries.flatten() {
        let name = entry.file_name();
        let Some(pid) = name.to_str().and_then(pid_of) else {
            continue;
        };
        // A directory entry's metadata is the link's own: a link named like a folder is not
        // followed.
        let ours = entry.metadata().is_ok_and(|m| m.is_dir() && m.uid() == me);
        if !ours {
            continue;
        }
        let path = entry.path();
        match remove_if_stale(&path, pid) {
            Ok(true) => {
                tracing::debug!(dir = %path.display(), "removed the runtime folder of a dead bootstrap")
            }
            Ok(false) => {}
            Err(e) => {
                tracing::debug!(dir = %path.display(), error = %e, "cannot remove a stale runtime folder")
            }
        }
    }
}

/// Removes the folder at `path` if its bootstrap is dead: `Ok(true)`; `Ok(false)`: left (its
/// bootstrap runs, or another folder has the name now); `Err`: it could not be opened,
/// locked or removed.
fn remove_if_stale(path: &Path, pid: libc::pid_t) -> std::io::Result<bool> {
    let dir = File::open(path)?;
    match dir.try_lock() {
        Ok(()) => {}
        // Locked: its bootstrap runs.
        Err(TryLockError::WouldBlock) => return Ok(false),
        // No lock on this file system: nothing tells a live folder, so none is removed.
        Err(TryLockError::Error(e)) => return Err(e),
    }
    // Locked, and still the folder at that name? (Another sweep may have removed it and a
    // bootstrap made a new one meanwhile.) While the lock is held no bootstrap makes one there.
    // Not locked before, but its pid is another running `s3res-bootstrap`: one too old to lock.
    if !same_file(&dir, path) || is_other_bootstrap(pid) {
        return Ok(false);
    }
    match std::fs::remove_dir_all(path) {
        Ok(()) => Ok(true),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(true),
        Err(e) => Err(e),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tmp() -> tempfile::TempDir {
        tempfile::Builder::new()
            .prefix("s3res-runtime-test-")
            .tempdir()
            .unwrap()
    }

    #[test]
    fn names_of_runtime_folders_and_nothing_else() {
        assert_eq!(pid_of("s3res-1234-0"), Some(1234));
        assert_eq!(pid_of("s3res-1-17"), Some(1));
        for other in [
            "s3res-test-abc",
            "s3res-inject-x1",
            "s3res-12-x",
            "s3res-12",
            "s3res--0",
            "other-12-0",
        ] {
            assert_eq!(pid_of(other), None, "{other}");
        }
    }

    /// A folder whose lock is held is left whatever its pid says (here: a pid that cannot
    /// exist); once the lock is let go, the next sweep removes it.
    #[test]
    fn a_locked_folder_is_live_whatever_its_pid() {
        let t = tmp();
        let path = t.path().join("s3res-2147483646-0");
        std::fs::create_dir(&path).unwrap();
        std::fs::write(path.join("v1.sock"), b"").unwrap();
        let holder = File::open(&path).unwrap();
        holder.try_lock().unwrap();
        remove_stale(t.path());
        assert!(path.join("v1.sock").exists(), "a locked folder was removed");
        drop(holder);
        remove_stale(t.path());
        assert!(!path.exists(), "an unlocked folder of a dead pid stays");
    }

    /// What `make` returns is locked against every other sweep, and a second `make` in the
    /// same folder (one process, so the same pid) takes the next name.
    #[test]
    fn a_made_folder_is_locked_and_the_next_takes_the_next_name() {
        let t = tmp();
        let first = make(t.path()).unwrap();
        assert!(first._lock.is_some(), "tmpfs and ext4 take locks");
        let pid = std::process::id();
        assert_eq!(first.path, t.path().join(format!("s3res-{pid}-0")));
        let other = File::open(&first.path).unwrap();
        assert!(matches!(other.try_lock(), Err(TryLockError::WouldBlock)));
        let second = make(t.path()).unwrap();
        assert_eq!(second.path, t.path().join(format!("s3res-{pid}-1")));
        assert!(
            first.path.is_dir(),
            "the second make removed the first's folder"
        );
    }

    /// A folder others can enter is refused, with what the file system made of it.
    #[test]
    fn a_folder_open_to_others_is_not_private() {
        use std::os::unix::fs::PermissionsExt;
        let t = tmp();
        let path = t.path().join("d");
        std::fs::create_dir(&path).unwrap();
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o700)).unwrap();
        check_private(&File::open(&path).unwrap()).unwrap();
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o750)).unwrap();
        let e = check_private(&File::open(&path).unwrap()).unwrap_err();
        assert!(e.to_string().contains("with mode 750"), "{e}");
        assert!(e.to_string().contains("set TMPDIR"), "{e}");
    }

    /// A link named like a runtime folder is not followed, and the sweep leaves folders of
    /// names it does not know.
    #[test]
    fn a_sweep_leaves_links_and_other_names() {
        let t = tmp();
        let target = t.path().join("kept");
        std::fs::create_dir(&target).unwrap();
        std::os::unix::fs::symlink(&target, t.path().join("s3res-2147483646-1")).unwrap();
        std::fs::create_dir(t.path().join("s3res-tmp-x")).unwrap();
        remove_stale(t.path());
        assert!(target.is_dir());
        assert!(t.path().join("s3res-2147483646-1").exists());
        assert!(t.path().join("s3res-tmp-x").is_dir());
    }
}
