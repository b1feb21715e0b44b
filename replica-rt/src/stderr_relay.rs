//! A child's stderr, relayed line by line behind a prefix that says who wrote it, and what it
//! said last (for the line that reports its death).
//!
//! The voter relays each replica's: every replica writes its stderr into a pipe of its own (a
//! fork child gets a fresh one at the handover, on fd 2), and the voter writes each whole line
//! to its own stderr behind `[component#slot pid N]`. So every line says which replica wrote
//! it — a fork child under its own slot, not its donor's —, lines of different replicas never
//! run into each other, and what a replica wrote just before it died is still read to the end
//! (the budget's message quotes the last line). bootstrap relays each unprotected component's
//! behind `[component pid N]`, from a thread, with a sink that prints above its status line.

use std::io::Write as _;
use std::os::fd::{AsFd, OwnedFd};

use crate::sys;

/// Longest line kept whole; a longer one is cut there (and the rest follows as a line).
const MAX_LINE: usize = 4096;
/// At most this much is read at one call, so that a replica that floods its stderr cannot keep
/// the event loop from its rounds.
const READ_LIMIT: usize = 64 * 1024;

/// What a relay knows of its replica's words: [`StderrRelay::memory`].
#[derive(Debug, Clone)]
pub struct StderrMemory {
    last_line: String,
    in_causes: bool,
    partial: Vec<u8>,
}

/// The voter's end of one replica's stderr pipe.
#[derive(Debug)]
pub struct StderrRelay {
    fd: Option<OwnedFd>,
    partial: Vec<u8>,
    /// The last whole line that says something (without the prefix): not a backtrace frame
    /// (indented) nor its heading, so that after a panic it is the panic's message; an error
    /// report's causes (anyhow's indented lines under `Caused by:`) are joined to it, since the
    /// cause is often the part that says what to fix.
    pub last_line: String,
    /// Lines read now are the causes of `last_line`'s error.
    in_causes: bool,
}

impl StderrRelay {
    /// Takes the non-blocking read end of the pipe.
    pub fn new(fd: OwnedFd) -> StderrRelay {
        StderrRelay {
            fd: Some(fd),
            partial: Vec::new(),
            last_line: String::new(),
            in_causes: false,
        }
    }

    /// The fd to wait on, while the pipe is open.
    pub fn fd(&self) -> Option<&OwnedFd> {
        self.fd.as_ref()
    }

    /// Reads what the pipe holds now (at most [`READ_LIMIT`]) and writes every whole line to
    /// our stderr behind `prefix`. At the end of the pipe the last partial line goes out too.
    pub fn relay(&mut self, prefix: &str) {
        self.relay_to(prefix, &mut |line| {
            let _ = std::io::stderr().lock().write_all(line);
        });
    }

    /// [`StderrRelay::relay`], each line (prefix, text and newline) given to `sink` whole. On
    /// a blocking pipe it waits for the first read, and returns after [`READ_LIMIT`] bytes or
    /// at the end of the pipe (then [`StderrRelay::fd`] is `None`).
    pub fn relay_to(&mut self, prefix: &str, sink: &mut dyn FnMut(&[u8])) {
        let mut buf = [0u8; 4096];
        let mut read = 0;
        while read < READ_LIMIT {
            let Some(fd) = self.fd.as_ref() else { return };
            match sys::read(fd.as_fd(), &mut buf) {
                Ok(0) => {
                    self.fd = None;
                    if !self.partial.is_empty() {
                        let rest = std::mem::take(&mut self.partial);
                        self.emit(prefix, &rest, sink);
                    }
                    return;
                }
                Ok(n) => {
                    read += n;
                    self.take(prefix, &buf[..n], sink);
                }
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => return,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(_) => {
                    self.fd = None;
                    return;
                }
            }
        }
    }

    /// What this relay knows of what its replica said: for the relay of a fork child of it.
    pub fn memory(&self) -> StderrMemory {
        StderrMemory {
            last_line: self.last_line.clone(),
            in_causes: self.in_causes,
            partial: self.partial.clone(),
        }
    }

    /// A fork child's relay goes on from its donor's (taken just before the fork): what the
    /// donor said last is what the child said last until it says something itself, and a line
    /// the donor had begun is the child's to end (its memory is the donor's: a donor forked
    /// half-way through an error report has a child that writes only the rest of it).
    pub fn continue_from(&mut self, donor: &StderrMemory) {
        self.last_line.clone_from(&donor.last_line);
        self.in_causes = donor.in_causes;
        self.partial.clone_from(&donor.partial);
    }

    fn take(&mut self, prefix: &str, mut bytes: &[u8], sink: &mut dyn FnMut(&[u8])) {
        while let Some(nl) = bytes.iter().position(|&b| b == b'\n') {
            let mut line = std::mem::take(&mut self.partial);
            line.extend_from_slice(&bytes[..nl]);
            self.emit(prefix, &line, sink);
            bytes = &bytes[nl + 1..];
        }
        self.partial.extend_from_slice(bytes);
        while self.partial.len() >= MAX_LINE {
            let rest = self.partial.split_off(MAX_LINE);
            let line = std::mem::replace(&mut self.partial, rest);
            self.emit(prefix, &line, sink);
        }
    }

    /// One line out, in one write (so that lines of the voter and of other replicas never mix).
    fn emit(&mut self, prefix: &str, line: &[u8], sink: &mut dyn FnMut(&[u8])) {
        let text = String::from_utf8_lossy(line);
        let text = text.trim_end_matches('\r');
        let mut out = Vec::with_capacity(prefix.len() + text.len() + 1);
        out.extend_from_slice(prefix.as_bytes());
        out.extend_from_slice(text.as_bytes());
        out.push(b'\n');
        sink(&out);
        // std's panic says "stack backtrace:", anyhow's error report "Stack backtrace:".
        let heading = text.to_ascii_lowercase();
        // anyhow's heading is the whole line (a JVM's `Caused by: java.io…` is a line of its
        // own, and its frames `\tat …` are no causes).
        if text == "Caused by:" {
            self.in_causes = true;
            return;
        }
        let indented = text.starts_with(char::is_whitespace);
        if self.in_causes && text.starts_with("    ") && !text.trim().is_empty() {
            // `    no such port`, or with several causes `    0: no such port`.
            let cause = text.trim();
            let cause = match cause.split_once(": ") {
                Some((n, rest)) if n.bytes().all(|b| b.is_ascii_digit()) => rest,
                _ => cause,
            };
            if self.last_line.len() + cause.len() + 2 <= MAX_LINE {
                self.last_line.push_str(": ");
                self.last_line.push_str(cause);
            }
            return;
        }
        if !indented {
            self.in_causes = false;
        }
        let says = !text.trim().is_empty()
            && !indented
            && !heading.starts_with("stack backtrace")
            && !heading.starts_with("backtrace:")
            && !text.starts_with("note: ");
        if says {
            self.last_line = text.to_owned();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn relay_of(chunks: &[&[u8]]) -> (StderrRelay, Vec<String>) {
        let (r, w) = sys::pipe().unwrap();
        sys::set_nonblocking(r.as_fd(), true).unwrap();
        let mut relay = StderrRelay::new(r);
        let mut lasts = Vec::new();
        for c in chunks {
            sys::write(w.as_fd(), c).unwrap();
            relay.relay("[t#0 pid 1] ");
            lasts.push(relay.last_line.clone());
        }
        drop(w);
        relay.relay("[t#0 pid 1] ");
        lasts.push(relay.last_line.clone());
        (relay, lasts)
    }

    /// The relay of a fork child of `donor` that wrote `wrote` and ended.
    fn child_of(donor: &StderrRelay, wrote: &[u8]) -> StderrRelay {
        let (r, w) = sys::pipe().unwrap();
        sys::set_nonblocking(r.as_fd(), true).unwrap();
        let mut child = StderrRelay::new(r);
        child.continue_from(&donor.memory());
        sys::write(w.as_fd(), wrote).unwrap();
        drop(w);
        child.relay("[t#1 pid 2] ");
        child
    }

    #[test]
    fn lines_are_relayed_whole_and_the_last_one_is_kept() {
        let (relay, lasts) = relay_of(&[b"first li", b"ne\nsecond\nthi", b"rd without newline"]);
        assert_eq!(lasts, ["", "second", "second", "third without newline"]);
        assert!(relay.fd().is_none(), "closed at the end of the pipe");
    }

    #[test]
    fn the_last_line_that_says_something_is_kept_not_a_backtrace_frame() {
        let (_, lasts) = relay_of(&[
            b"panicked at src/main.rs:3:5:\nboom\nstack backtrace:\n   0: main\n             at x.rs:1\n",
        ]);
        assert_eq!(lasts[0], "boom");
    }

    #[test]
    fn an_error_report_with_a_backtrace_keeps_its_message() {
        let (_, lasts) = relay_of(&[
            b"Error: opening port `in`\n\nCaused by:\n    no such port\n\nStack backtrace:\n   0: main\n",
        ]);
        assert_eq!(lasts[0], "Error: opening port `in`: no such port");
    }

    #[test]
    fn every_cause_of_an_error_report_is_kept() {
        let (_, lasts) = relay_of(&[
            b"Error: starting

Caused by:
    0: opening port `in`
    1: no such port
",
            b"a later line
",
        ]);
        assert_eq!(lasts[0], "Error: starting: opening port `in`: no such port");
        assert_eq!(lasts[1], "a later line");
    }

    #[test]
    fn a_jvm_trace_is_not_taken_for_an_error_report() {
        let (_, lasts) = relay_of(&[
            b"Exception in thread \"main\" java.lang.RuntimeException: boom\n\tat A.b(A.java:3)\nCaused by: java.io.IOException: disk\n\tat C.d(C.java:9)\n",
        ]);
        assert_eq!(lasts[0], "Caused by: java.io.IOException: disk");
    }

    #[test]
    fn a_fork_child_that_writes_only_a_backtrace_is_quoted_with_its_donors_error() {
        let (donor, _) = relay_of(&[b"Error: opening port `in`\n\nCaused by:\n"]);
        let child = child_of(
            &donor,
            b"    no such port\n\nStack backtrace:\n   0: main\n",
        );
        assert_eq!(child.last_line, "Error: opening port `in`: no such port");
    }

    /// A donor forked in the middle of a line (its report written in pieces): the child ends
    /// that line, not an older one.
    #[test]
    fn a_fork_child_ends_the_line_its_donor_began() {
        let (donor, _) = relay_of(&[b"WARN something earlier\nError: opening port `in`"]);
        let child = child_of(&donor, b"\n\nCaused by:\n    no such port\n");
        assert_eq!(child.last_line, "Error: opening port `in`: no such port");
    }

    #[test]
    fn a_long_line_is_cut() {
        let long = vec![b'x'; MAX_LINE + 10];
        let (_, lasts) = relay_of(&[&long]);
        assert_eq!(lasts[0].len(), MAX_LINE);
        assert_eq!(lasts[1].len(), 10);
    }
}
