//! Every command block of README.md and docs/*.md marked runnable (a fenced block whose info
//! string is `sh runnable`) runs, and succeeds, as a user would type it from the repository's
//! root. So the commands the docs tell people to type stay true.
//!
//! How a block is run:
//! - in a fresh folder holding what the commands name from the repository (`examples/`,
//!   `inject/`, `system.json`) and `target/release/`, which points at the executables the test
//!   harness built (the test profile's: the commands do not depend on the build profile);
//! - `cargo build …` steps are left out (the harness built everything), and so is a leading
//!   `cargo build … &&`;
//! - counts are made small: `--runs N` becomes `--runs 2`;
//! - with `bash -e -o pipefail`, in its own process group, with an environment mark; bounded
//!   in time, after which the group is killed and the test fails; whatever carries the mark
//!   afterwards is killed and fails the test.

use std::os::unix::process::CommandExt as _;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// Bound on one block (the longest is one robot mission under fire, about half a minute).
const LIMIT: Duration = Duration::from_secs(300);
/// The mark every process of a block inherits.
const MARK: &str = "S3RES_DOC_BLOCK";
/// The info string of a runnable block.
const TAG: &str = "sh runnable";

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("bootstrap/ is in the repository")
        .to_path_buf()
}

/// `(file, line, commands)` of every runnable block in `text`.
fn runnable_blocks(file: &str, text: &str) -> Vec<(String, usize, String)> {
    let mut out = Vec::new();
    let mut open: Option<(usize, String)> = None;
    for (i, line) in text.lines().enumerate() {
        let fence = line.trim_start().starts_with("```");
        match &mut open {
            None if fence && line.trim_start().trim_start_matches('`').trim() == TAG => {
                open = Some((i + 1, String::new()));
            }
            Some((at, body)) if fence => {
                out.push((file.to_owned(), *at, std::mem::take(body)));
                open = None;
            }
            Some((_, body)) => {
                body.push_str(line);
                body.push('\n');
            }
            None => {}
        }
    }
    out
}

/// The block as the test runs it (see the module docs).
fn prepared(block: &str) -> String {
    let mut out = String::new();
    for line in block.lines() {
        let line = line.trim_start();
        let line = match line.split_once("&& ") {
            Some((first, rest)) if first.trim_start().starts_with("cargo build") => rest,
            _ if line.starts_with("cargo build") => continue,
            _ => line,
        };
        let mut words: Vec<String> = Vec::new();
        for w in line.split(' ') {
            if words.last().is_some_and(|p| p == "--runs") && w.parse::<u64>().is_ok() {
                words.push("2".to_owned());
            } else {
                words.push(w.to_owned());
            }
        }
        out.push_str(&words.join(" "));
        out.push('\n');
    }
    out
}

/// A fresh folder laid out like the repository's root for the commands.
fn workdir() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    let root = repo();
    for name in ["examples", "inject", "system.json"] {
        std::os::unix::fs::symlink(root.join(name), dir.path().join(name)).unwrap();
    }
    std::fs::create_dir(dir.path().join("target")).unwrap();
    std::os::unix::fs::symlink(
        s3res_testkit::bin_dir(),
        dir.path().join("target").join("release"),
    )
    .unwrap();
    dir
}

/// Runs one block; `Err` says what went wrong.
fn run_block(file: &str, line: usize, block: &str) -> Result<(), String> {
    let dir = workdir();
    let script = prepared(block);
    let mark = format!("{}-{file}-{line}", std::process::id());
    let log = dir.path().join("output.txt");
    let mut child = Command::new("bash")
        .args(["-e", "-o", "pipefail", "-c", &script])
        .current_dir(dir.path())
        .env(MARK, &mark)
        .stdin(Stdio::null())
        .stdout(std::fs::File::create(&log).unwrap())
        .stderr(std::fs::File::create(dir.path().join("stderr.txt")).unwrap())
        .process_group(0)
        .spawn()
        .map_err(|e| format!("starting bash: {e}"))?;
    let pgid = child.id() as i32;
    let deadline = Instant::now() + LIMIT;
    let status = loop {
        if let Some(st) = child.try_wait().map_err(|e| e.to_string())? {
            break Some(st);
        }
        if Instant::now() >= deadline {
            let _ = s3res_testkit::kill_pid(-pgid, libc::SIGKILL);
            let _ = child.wait();
            break None;
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let left = s3res_testkit::procs::kill_with_env(MARK, &mark);
    let stderr = std::fs::read_to_string(dir.path().join("stderr.txt")).unwrap_or_default();
    let tail = s3res_testkit::tail(&stderr, 30);
    match status {
        None => Err(format!(
            "{file}:{line}: did not end within {LIMIT:?}\n{script}\n{tail}"
        )),
        Some(st) if !st.success() => Err(format!("{file}:{line}: {st}\n{script}\n{tail}")),
        Some(_) if !left.is_empty() => Err(format!("{file}:{line}: left {left:?} behind")),
        Some(_) => Ok(()),
    }
}

#[test]
fn the_runnable_blocks_are_found_and_prepared() {
    let text = "a\n```sh runnable\ncargo build --release && x --runs 100 --seed 1\ncargo build\ny\n```\n```sh\nz\n```\n";
    let blocks = runnable_blocks("t.md", text);
    assert_eq!(blocks.len(), 1);
    assert_eq!(blocks[0].1, 2);
    assert_eq!(prepared(&blocks[0].2), "x --runs 2 --seed 1\ny\n");
}

#[test]
fn every_runnable_block_of_the_docs_runs() {
    let root = repo();
    let mut files = vec![root.join("README.md")];
    let mut docs: Vec<PathBuf> = std::fs::read_dir(root.join("docs"))
        .unwrap()
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "md"))
        .collect();
    docs.sort();
    files.extend(docs);
    let mut blocks = Vec::new();
    for f in &files {
        let name = f.strip_prefix(&root).unwrap_or(f).display().to_string();
        blocks.extend(runnable_blocks(&name, &std::fs::read_to_string(f).unwrap()));
    }
    assert!(
        blocks.iter().any(|b| b.0 == "README.md"),
        "README.md has no runnable block: {blocks:?}"
    );
    let mut failed = Vec::new();
    for (file, line, block) in &blocks {
        eprintln!("running {file}:{line}");
        if let Err(e) = run_block(file, *line, block) {
            failed.push(e);
        }
    }
    assert!(failed.is_empty(), "{}", failed.join("\n\n"));
}
