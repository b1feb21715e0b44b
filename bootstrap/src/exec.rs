//! Finding executables: a component's `exec`, and the `s3res-voter` binary.
//!
//! A value with a `/` is a path (relative ones start at the description's folder, so a system
//! and its scripts can live together). A bare name is looked for first beside the running
//! `s3res-bootstrap` — so `target/debug` and `target/release` work without installing — and
//! then on `PATH`.

use std::ffi::OsStr;
use std::os::unix::fs::PermissionsExt;
use std::path::{Component, Path, PathBuf};

use nix::unistd::{access, AccessFlags};

/// Where to look for bare names.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct SearchPath {
    /// Folder of the running s3res-bootstrap, searched first.
    pub self_dir: Option<PathBuf>,
    /// Folders of `PATH`, in order.
    pub path_dirs: Vec<PathBuf>,
}

impl SearchPath {
    /// From the running process: `current_exe`'s folder and `$PATH`.
    pub fn from_environment() -> Self {
        let self_dir = std::env::current_exe()
            .ok()
            .and_then(|p| p.parent().map(Path::to_path_buf));
        let path_dirs = std::env::var_os("PATH")
            .map(|p| split_path(&p))
            .unwrap_or_default();
        SearchPath {
            self_dir,
            path_dirs,
        }
    }

    /// The first executable file called `name` in the search folders.
    pub fn find(&self, name: &str) -> Result<PathBuf, String> {
        let mut not_executable: Option<PathBuf> = None;
        for dir in self.self_dir.iter().chain(self.path_dirs.iter()) {
            let candidate = dir.join(name);
            match check_executable(&candidate) {
                Ok(()) => return Ok(absolute(&candidate)),
                Err(ExecProblem::Missing) => {}
                Err(_) => {
                    not_executable.get_or_insert(candidate);
                }
            }
        }
        Err(match not_executable {
            Some(p) => format!(
                "`{name}` was found at {} but it is not an executable file",
                p.display()
            ),
            None => format!("`{name}` was not found beside s3res-bootstrap nor on PATH"),
        })
    }
}

fn split_path(p: &OsStr) -> Vec<PathBuf> {
    std::env::split_paths(p)
        // An empty PATH entry means the current directory; searching it silently would make
        // the result depend on where bootstrap was started, so it is skipped.
        .filter(|d| !d.as_os_str().is_empty())
        .collect()
}

/// One of s3res's own programs: the path in environment variable `env` if set (relative to
/// the current folder, or a bare name looked up like `exec`), else `name` beside the running
/// program or on `PATH`.
pub fn find_tool(name: &str, env: &str) -> Result<PathBuf, String> {
    let search = SearchPath::from_environment();
    match std::env::var(env) {
        Ok(path) => {
            let cwd = std::env::current_dir().map_err(|e| format!("no current folder: {e}"))?;
            resolve(&path, &cwd, &search).map_err(|e| format!("{env}: {e}"))
        }
        Err(_) => search.find(name),
    }
}

/// Resolves a component's `exec` value to an absolute path of an executable file.
pub fn resolve(value: &str, base_dir: &Path, search: &SearchPath) -> Result<PathBuf, String> {
    if value.is_empty() {
        return Err("exec is empty".to_owned());
    }
    if !value.contains('/') {
        return search.find(value);
    }
    let path = absolute(&base_dir.join(value));
    match check_executable(&path) {
        Ok(()) => Ok(path),
        Err(ExecProblem::Missing) => Err(format!(
            "executable `{value}` does not exist (looked at {})",
            path.display()
        )),
        Err(ExecProblem::NotAFile) => Err(format!(
            "executable `{value}` is not a file ({})",
            path.display()
        )),
        Err(ExecProblem::NotExecutable) => Err(format!(
            "`{value}` is not executable (no execute permission on {})",
            path.display()
        )),
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum ExecProblem {
    Missing,
    NotAFile,
    NotExecutable,
}

fn check_executable(path: &Path) -> Result<(), ExecProblem> {
    let meta = std::fs::metadata(path).map_err(|_| ExecProblem::Missing)?;
    if !meta.is_file() {
        return Err(ExecProblem::NotAFile);
    }
    // access(X_OK) answers for *this* user; the mode check catches root, for whom access
    // succeeds on a regular file only if some execute bit is set anyway, but says so plainly.
    if meta.permissions().mode() & 0o111 == 0 || access(path, AccessFlags::X_OK).is_err() {
        return Err(ExecProblem::NotExecutable);
    }
    Ok(())
}

/// `path` made absolute against the current directory, with `.` parts dropped and `..` folded
/// lexically (the stored path is for display and exec; symlinks are left alone).
pub fn absolute(path: &Path) -> PathBuf {
    let joined = if path.is_absolute() {
        path.to_path_buf()
    } else {
        std::env::current_dir()
            .map(|d| d.join(path))
            .unwrap_or_else(|_| path.to_path_buf())
    };
    let mut out = PathBuf::new();
    for c in joined.components() {
        match c {
            Component::CurDir => {}
            Component::ParentDir => {
                out.pop();
            }
            other => out.push(other.as_os_str()),
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::fs;

    fn make_file(dir: &Path, name: &str, mode: u32) -> PathBuf {
        let p = dir.join(name);
        fs::write(&p, "#!/bin/sh\n").unwrap();
        fs::set_permissions(&p, fs::Permissions::from_mode(mode)).unwrap();
        p
    }

    #[test]
    fn relative_paths_start_at_the_description_folder() {
        let dir = tempfile::tempdir().unwrap();
        make_file(dir.path(), "run.sh", 0o755);
        let got = resolve("./run.sh", dir.path(), &SearchPath::default()).unwrap();
        assert_eq!(got, dir.path().join("run.sh"));
        let sub = dir.path().join("sub");
        fs::create_dir(&sub).unwrap();
        let got = resolve("../run.sh", &sub, &SearchPath::default()).unwrap();
        assert_eq!(got, dir.path().join("run.sh"));
    }

    #[test]
    fn missing_and_not_executable_are_told_apart() {
        let dir = tempfile::tempdir().unwrap();
        make_file(dir.path(), "plain.txt", 0o644);
        let e = resolve("./nope", dir.path(), &SearchPath::default()).unwrap_err();
        assert!(e.contains("does not exist"), "{e}");
        let e = resolve("./plain.txt", dir.path(), &SearchPath::default()).unwrap_err();
        assert!(e.contains("not executable"), "{e}");
        let e = resolve("./", dir.path(), &SearchPath::default()).unwrap_err();
        assert!(e.contains("not a file"), "{e}");
        let e = resolve("", dir.path(), &SearchPath::default()).unwrap_err();
        assert!(e.contains("empty"), "{e}");
    }

    #[test]
    fn bare_names_prefer_the_bootstrap_folder_then_path() {
        let own = tempfile::tempdir().unwrap();
        let on_path = tempfile::tempdir().unwrap();
        make_file(own.path(), "tool", 0o755);
        make_file(on_path.path(), "tool", 0o755);
        make_file(on_path.path(), "other", 0o755);
        make_file(own.path(), "noexec", 0o644);
        let search = SearchPath {
            self_dir: Some(own.path().to_path_buf()),
            path_dirs: vec![on_path.path().to_path_buf()],
        };
        let base = Path::new("/");
        assert_eq!(
            resolve("tool", base, &search).unwrap(),
            own.path().join("tool")
        );
        assert_eq!(
            resolve("other", base, &search).unwrap(),
            on_path.path().join("other")
        );
        let e = resolve("noexec", base, &search).unwrap_err();
        assert!(e.contains("not an executable"), "{e}");
        let e = resolve("absent", base, &search).unwrap_err();
        assert!(
            e.contains("not found beside s3res-bootstrap nor on PATH"),
            "{e}"
        );
    }

    #[test]
    fn absolute_folds_dots() {
        assert_eq!(absolute(Path::new("/a/./b/../c")), PathBuf::from("/a/c"));
        assert!(absolute(Path::new("x")).is_absolute());
    }

    #[test]
    fn empty_path_entries_are_skipped() {
        let dirs = split_path(OsStr::new("/bin::/usr/bin"));
        assert_eq!(dirs, vec![PathBuf::from("/bin"), PathBuf::from("/usr/bin")]);
    }
}
