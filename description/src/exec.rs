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
                Ok(()) => {
                    return match interpreter_problem(&candidate, &self.path_dirs) {
                        None => Ok(absolute(&candidate)),
                        Some(why) => Err(format!("`{name}` ({}): {why}", candidate.display())),
                    }
                }
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
        Ok(()) => match interpreter_problem(&path, &search.path_dirs) {
            None => Ok(path),
            Some(why) => Err(format!("`{value}`: {why}")),
        },
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

/// Why the `#!` line of the script at `path`, if it is one, would make its exec fail: the
/// interpreter it names is missing or not executable, or — for `#!/usr/bin/env NAME` — NAME is
/// on none of `path_dirs` (the `PATH` the component inherits). Without this check a missing
/// interpreter passes `--check` and the start fails with "No such file or directory", which
/// names the script, not what is missing.
fn interpreter_problem(path: &Path, path_dirs: &[PathBuf]) -> Option<String> {
    use std::io::Read;
    // The kernel reads at most this much of a `#!` line (BINPRM_BUF_SIZE).
    let mut head = [0u8; 256];
    let n = std::fs::File::open(path)
        .and_then(|mut f| f.read(&mut head))
        .ok()?;
    let line = head[..n].strip_prefix(b"#!")?;
    let line = line.split(|&b| b == b'\n').next().unwrap_or_default();
    let line = String::from_utf8_lossy(line);
    let mut words = line.split_whitespace();
    let Some(interpreter) = words.next() else {
        return Some("its `#!` line names no interpreter".to_owned());
    };
    match check_executable(Path::new(interpreter)) {
        Ok(()) => {}
        Err(ExecProblem::Missing) => {
            return Some(format!(
                "its `#!` line names the interpreter {interpreter}, which does not exist"
            ))
        }
        Err(_) => {
            return Some(format!(
                "its `#!` line names the interpreter {interpreter}, which is not an executable \
                 file"
            ))
        }
    }
    // `#!/usr/bin/env NAME`: env looks NAME up on PATH when the script starts. An option
    // (`-S …`) or an assignment is left to env.
    let is_env = Path::new(interpreter).file_name() == Some(OsStr::new("env"));
    match words.next() {
        Some(name) if is_env && !name.starts_with('-') && !name.contains('=') => {
            let found = if name.contains('/') {
                check_executable(Path::new(name)).is_ok()
            } else {
                path_dirs
                    .iter()
                    .any(|d| check_executable(&d.join(name)).is_ok())
            };
            (!found).then(|| {
                format!("its `#!` line runs `{interpreter} {name}`, and {name} is not on PATH")
            })
        }
        _ => None,
    }
}

/// File name of the preload library (the `s3res-preload` crate's cdylib).
pub const PRELOAD_LIBRARY: &str = "libs3res_preload.so";

/// Environment variable naming the preload library to use instead of the one beside
/// s3res-bootstrap.
pub const PRELOAD_ENV: &str = "S3RES_PRELOAD";

/// The preload library: `$S3RES_PRELOAD`, else [`PRELOAD_LIBRARY`] beside the running
/// s3res-bootstrap (where cargo builds it).
pub fn find_preload_library() -> Result<PathBuf, String> {
    if let Some(path) = std::env::var_os(PRELOAD_ENV) {
        let path = absolute(Path::new(&path));
        return if path.is_file() {
            Ok(path)
        } else {
            Err(format!("{PRELOAD_ENV}={} is not a file", path.display()))
        };
    }
    let beside = SearchPath::from_environment()
        .self_dir
        .map(|d| d.join(PRELOAD_LIBRARY));
    match beside {
        Some(p) if p.is_file() => Ok(absolute(&p)),
        Some(p) => Err(format!(
            "the preload library was not found at {} (build the workspace with `cargo build`, \
             or set {PRELOAD_ENV})",
            p.display()
        )),
        None => Err(format!(
            "no folder for s3res-bootstrap, so no {PRELOAD_LIBRARY}; set {PRELOAD_ENV}"
        )),
    }
}

/// Why `LD_PRELOAD` cannot reach the program at `path`, if it cannot: a setuid or setgid
/// program (the dynamic linker ignores `LD_PRELOAD` for it), a statically linked executable
/// (there is no dynamic linker), or a file that is neither an ELF executable nor a `#!` script.
/// A script is judged by its interpreter.
pub fn preload_problem(path: &Path) -> Option<String> {
    preload_problem_at(path, 0)
}

fn preload_problem_at(path: &Path, depth: usize) -> Option<String> {
    use std::io::Read;
    let shown = path.display();
    let meta = std::fs::metadata(path).ok()?;
    if meta.permissions().mode() & 0o6000 != 0 {
        return Some(format!(
            "{shown} is setuid or setgid: the dynamic linker ignores LD_PRELOAD for it, so it \
             cannot run as an unmodified program"
        ));
    }
    let mut head = [0u8; 4096];
    let n = std::fs::File::open(path)
        .and_then(|mut f| f.read(&mut head))
        .ok()?;
    let head = &head[..n];
    if let Some(rest) = head.strip_prefix(b"#!") {
        let line = rest.split(|&b| b == b'\n').next().unwrap_or_default();
        let interpreter = String::from_utf8_lossy(line);
        let interpreter = interpreter.split_whitespace().next().unwrap_or_default();
        if interpreter.is_empty() || depth > 2 {
            return Some(format!("{shown}: a `#!` line without a usable interpreter"));
        }
        return preload_problem_at(Path::new(interpreter), depth + 1);
    }
    match elf_is_dynamic(head) {
        Some(true) => None,
        Some(false) => Some(format!(
            "{shown} is statically linked: LD_PRELOAD cannot reach it, so it cannot run as an \
             unmodified program (link it with libs3res_replica_c instead; see \
             docs/writing-a-component.md)"
        )),
        None => Some(format!(
            "{shown} is neither an ELF executable nor a `#!` script"
        )),
    }
}

/// Whether the ELF image starting with `head` asks for a dynamic linker (has `PT_INTERP`);
/// `None` if it is not ELF or its program headers are not within `head`.
fn elf_is_dynamic(head: &[u8]) -> Option<bool> {
    const PT_INTERP: u64 = 3;
    if head.len() < 0x40 || &head[..4] != b"\x7fELF" {
        return None;
    }
    let le = match head[5] {
        1 => true,
        2 => false,
        _ => return None,
    };
    // An unsigned field of `width` bytes at offset `o`, in the file's byte order.
    let field = |o: usize, width: usize| -> Option<u64> {
        let bytes = head.get(o..o.checked_add(width)?)?;
        let fold = |acc: u64, &b: &u8| acc << 8 | u64::from(b);
        Some(if le {
            bytes.iter().rev().fold(0, fold)
        } else {
            bytes.iter().fold(0, fold)
        })
    };
    let u16_at = |o| field(o, 2);
    let u32_at = |o| field(o, 4);
    let u64_at = |o| field(o, 8);
    let (phoff, phentsize, phnum) = match head[4] {
        1 => (u32_at(0x1c)?, u16_at(0x2a)?, u16_at(0x2c)?),
        2 => (u64_at(0x20)?, u16_at(0x36)?, u16_at(0x38)?),
        _ => return None,
    };
    for k in 0..phnum {
        let at = usize::try_from(phoff.checked_add(k.checked_mul(phentsize)?)?).ok()?;
        if u32_at(at)? == PT_INTERP {
            return Some(true);
        }
    }
    Some(false)
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

/// Why `path` cannot be a file bootstrap writes (an events, state or outcome file), as far as
/// the file system says now: it is a folder (`example` names a file to suggest in it), or a
/// folder on its way is a file. `None` if it can be (or its folders are still to be made). A
/// relative path is taken from the working folder.
pub fn not_a_file_path(path: &Path, example: &str) -> Option<String> {
    if path.is_dir() {
        return Some(format!(
            "`{}` is a folder: give the path of a file (e.g. `{}`)",
            path.display(),
            path.join(example).display()
        ));
    }
    // The nearest folder on the way that exists must be a folder.
    let mut up = path.parent();
    while let Some(dir) = up.filter(|d| !d.as_os_str().is_empty()) {
        match std::fs::metadata(dir) {
            Ok(m) if m.is_dir() => return None,
            Ok(_) => {
                return Some(format!(
                    "`{}` is a file, not a folder: `{}` cannot be made in it",
                    dir.display(),
                    path.display()
                ))
            }
            Err(_) => up = dir.parent(),
        }
    }
    None
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

    /// A script whose `#!` interpreter is missing (or, through `env`, not on PATH) is refused
    /// by name of what is missing; one whose interpreter is there passes.
    #[test]
    fn a_script_is_refused_when_its_interpreter_is_missing() {
        let dir = tempfile::tempdir().unwrap();
        let write = |name: &str, text: &str| {
            let p = dir.path().join(name);
            fs::write(&p, text).unwrap();
            fs::set_permissions(&p, fs::Permissions::from_mode(0o755)).unwrap();
        };
        write("ok.sh", "#!/bin/sh\necho hi\n");
        write("gone.sh", "#!/nonexistent/interp -x\n");
        write("env-gone.sh", "#!/usr/bin/env no-such-interpreter-s3res\n");
        write("env-ok.sh", "#!/usr/bin/env sh\n");
        write("empty.sh", "#!\n");
        let search = SearchPath {
            self_dir: None,
            path_dirs: vec!["/bin".into(), "/usr/bin".into()],
        };
        assert!(resolve("./ok.sh", dir.path(), &search).is_ok());
        let e = resolve("./gone.sh", dir.path(), &search).unwrap_err();
        assert!(
            e.contains("`./gone.sh`: its `#!` line names the interpreter /nonexistent/interp, which does not exist"),
            "{e}"
        );
        let e = resolve("./env-gone.sh", dir.path(), &search).unwrap_err();
        assert!(
            e.contains("no-such-interpreter-s3res is not on PATH"),
            "{e}"
        );
        if Path::new("/usr/bin/env").exists() {
            assert!(resolve("./env-ok.sh", dir.path(), &search).is_ok());
        }
        let e = resolve("./empty.sh", dir.path(), &search).unwrap_err();
        assert!(e.contains("names no interpreter"), "{e}");
        // Found by bare name, the same.
        let bare = SearchPath {
            self_dir: Some(dir.path().to_path_buf()),
            path_dirs: vec![],
        };
        let e = bare.find("gone.sh").unwrap_err();
        assert!(
            e.contains("/nonexistent/interp, which does not exist"),
            "{e}"
        );
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
    fn what_ld_preload_cannot_reach_is_named() {
        // The system's own awk or sh is dynamically linked (as on every distribution we know).
        let sh = Path::new("/bin/sh");
        assert_eq!(preload_problem(sh), None, "/bin/sh");
        let dir = tempfile::tempdir().unwrap();
        let script = dir.path().join("s.sh");
        fs::write(&script, "#!/bin/sh\necho hi\n").unwrap();
        assert_eq!(preload_problem(&script), None);
        let odd = make_file(dir.path(), "odd", 0o755);
        fs::write(&odd, "not a program").unwrap();
        let e = preload_problem(&odd).unwrap();
        assert!(e.contains("neither an ELF executable nor"), "{e}");
        let suid = dir.path().join("suid");
        fs::copy(sh, &suid).unwrap();
        fs::set_permissions(&suid, fs::Permissions::from_mode(0o4755)).unwrap();
        let e = preload_problem(&suid).unwrap();
        assert!(e.contains("setuid"), "{e}");
        // A minimal 64-bit ELF header with one PT_LOAD program header: static.
        let mut elf = vec![0u8; 0x40 + 56];
        elf[..4].copy_from_slice(b"\x7fELF");
        elf[4] = 2;
        elf[5] = 1;
        elf[0x20..0x28].copy_from_slice(&0x40u64.to_le_bytes());
        elf[0x36..0x38].copy_from_slice(&56u16.to_le_bytes());
        elf[0x38..0x3a].copy_from_slice(&1u16.to_le_bytes());
        elf[0x40..0x44].copy_from_slice(&1u32.to_le_bytes());
        assert_eq!(elf_is_dynamic(&elf), Some(false));
        elf[0x40..0x44].copy_from_slice(&3u32.to_le_bytes());
        assert_eq!(elf_is_dynamic(&elf), Some(true));
        let stat = dir.path().join("static");
        fs::write(&stat, {
            let mut e = elf.clone();
            e[0x40..0x44].copy_from_slice(&1u32.to_le_bytes());
            e
        })
        .unwrap();
        let e = preload_problem(&stat).unwrap();
        assert!(e.contains("statically linked"), "{e}");
        // Truncated or garbage headers are not ELF, never a panic.
        assert_eq!(elf_is_dynamic(&elf[..0x30]), None);
        elf[0x20..0x28].copy_from_slice(&u64::MAX.to_le_bytes());
        assert_eq!(elf_is_dynamic(&elf), None);
    }

    #[test]
    fn a_big_endian_32_bit_elf_is_read_in_its_own_byte_order() {
        // ELFCLASS32, ELFDATA2MSB: phoff at 0x1c, phentsize at 0x2a, phnum at 0x2c.
        let mut elf = vec![0u8; 0x40 + 2 * 32];
        elf[..4].copy_from_slice(b"\x7fELF");
        elf[4] = 1;
        elf[5] = 2;
        elf[0x1c..0x20].copy_from_slice(&0x40u32.to_be_bytes());
        elf[0x2a..0x2c].copy_from_slice(&32u16.to_be_bytes());
        elf[0x2c..0x2e].copy_from_slice(&2u16.to_be_bytes());
        elf[0x40..0x44].copy_from_slice(&1u32.to_be_bytes());
        assert_eq!(elf_is_dynamic(&elf), Some(false));
        // The second program header is PT_INTERP.
        elf[0x60..0x64].copy_from_slice(&3u32.to_be_bytes());
        assert_eq!(elf_is_dynamic(&elf), Some(true));
        // Read little-endian, the same bytes would be other numbers.
        elf[5] = 1;
        assert_eq!(elf_is_dynamic(&elf), None);
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
