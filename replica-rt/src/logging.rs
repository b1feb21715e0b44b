//! Logging set-up, the one place of the project that installs a `tracing` subscriber: for
//! components ([`init_logging`]: each line prefixed with who wrote it) and for the command-line
//! tools and the voter ([`init_cli_logging`]: verbosity from `-q`/`-v`), and how they print an
//! error with its causes ([`error_chain`]).

use std::fmt;
use std::io::IsTerminal;

use tracing::{Event, Subscriber};
use tracing_subscriber::filter::Targets;
use tracing_subscriber::fmt::format::{Format, Full, Writer};
use tracing_subscriber::fmt::{FmtContext, FormatEvent, FormatFields};
use tracing_subscriber::prelude::*;
use tracing_subscriber::registry::LookupSpan;
use tracing_subscriber::EnvFilter;

use crate::contract::{ENV_COMPONENT, ENV_REPLICA, ENV_VOTER_SOCKET};

/// Installs a `tracing` subscriber that writes to stderr, filtered by `RUST_LOG` (default
/// `info`; bootstrap passes its `-q`/`-v` on through it: see [`component_filter`]), each line
/// prefixed with `[component#replica pid N]`, and a panic hook that prefixes a panic's lines
/// the same way.
///
/// The component name is `S3RES_COMPONENT`, or `component_default` when the process was not
/// started by s3res (by hand, in a shell pipeline). A replica (started by a voter) writes no
/// prefix: its stderr is a pipe of its own that the voter reads, and the voter writes each line
/// behind `[component#slot pid N]` (a fork child under its own slot). Calling it again is
/// harmless (the first subscriber stays).
pub fn init_logging(component_default: &str) {
    let component = std::env::var(ENV_COMPONENT).unwrap_or_else(|_| component_default.to_owned());
    // A replica's stderr is a pipe its voter reads: the voter puts `[component#slot pid N]`
    // before each line itself, from its own bookkeeping (a fork child's slot is not its
    // donor's), so the replica writes none.
    let prefix = match std::env::var(ENV_REPLICA) {
        _ if std::env::var_os(ENV_VOTER_SOCKET).is_some() => None,
        Ok(r) => Some(format!("{component}#{r}")),
        Err(_) => Some(component),
    };
    let filter = component_filter(std::env::var("RUST_LOG").ok().as_deref());
    install_panic_hook(prefix.clone());
    let layer = tracing_subscriber::fmt::layer()
        .with_writer(std::io::stderr)
        .with_ansi(std::io::stderr().is_terminal())
        .event_format(Prefixed {
            prefix,
            inner: Format::default(),
        });
    // Err only if a subscriber is already set, which is what "harmless" above means.
    let _ = tracing_subscriber::registry()
        .with(filter)
        .with(layer)
        .try_init();
}

/// A component's log filter from `RUST_LOG`: a level (`warn`, `debug`, what bootstrap passes
/// on for `-q`/`-v`), and levels per target (`info,replica_rt=debug`), read directive by
/// directive: empty ones are skipped, as `EnvFilter` skips them, and one `Targets` cannot read
/// (a span or field filter, `foo[{x=1}]=debug`, or a typo) is left out rather than the whole
/// value. None that reads, or no `RUST_LOG`: `info`.
///
/// Components take `Targets`, not the `EnvFilter` of the voter and the tools: its span and
/// field directives need a regular-expression engine, about 250 KiB of machine code that every
/// replica would otherwise map, lock and keep resident (`s3res-echo`: 4,388 KiB resident under
/// `lock_memory: all` with it, 3,748 KiB without; docs/results.md).
pub fn component_filter(rust_log: Option<&str>) -> Targets {
    let mut filter = Targets::new();
    let mut read_any = false;
    let directives = rust_log.unwrap_or("").split(',').map(str::trim);
    let readable = directives
        .filter(|d| !d.is_empty())
        .filter_map(|d| d.parse::<Targets>().ok());
    for one in readable {
        read_any = true;
        if let Some(level) = one.default_level() {
            filter = filter.with_default(level);
        }
        for (target, level) in &one {
            filter = filter.with_target(target, level);
        }
    }
    if read_any {
        filter
    } else {
        Targets::new().with_default(tracing::Level::INFO)
    }
}

/// A panic is reported like a log line: every line of the message (and of the backtrace, with
/// `RUST_BACKTRACE` set) carries the `[name pid N]` prefix, and the whole report goes out in
/// one `write`, so lines of a dying replica are neither run together nor interleaved.
fn install_panic_hook(prefix: Option<String>) {
    std::panic::set_hook(Box::new(move |info| {
        let head = match &prefix {
            Some(prefix) => format!("[{prefix} pid {}] ", std::process::id()),
            None => String::new(),
        };
        let mut text = info.to_string();
        let trace = std::backtrace::Backtrace::capture();
        if trace.status() == std::backtrace::BacktraceStatus::Captured {
            text.push_str(&format!("\nbacktrace:\n{trace}"));
        }
        let report = prefix_lines(&head, &text);
        let _ = std::io::Write::write_all(&mut std::io::stderr().lock(), report.as_bytes());
    }));
}

/// `text` with `head` before every line, each line ending in a newline.
fn prefix_lines(head: &str, text: &str) -> String {
    let mut out = String::with_capacity(text.len() + head.len() * 4);
    for line in text.lines() {
        out.push_str(head);
        out.push_str(line);
        out.push('\n');
    }
    out
}

/// Logs to stderr at `info` (`-q`: `warn`; `-v`: `debug`; `-vv`: `trace`); `RUST_LOG`, when
/// set, takes precedence. Colours only on a terminal. For the command-line tools (bootstrap,
/// the injector, the trainer) and the voter; `init_cli_logging(false, 0)` is plain `info`.
/// Calling it again is harmless (the first subscriber stays).
pub fn init_cli_logging(quiet: bool, verbose: u8) {
    init_cli_logging_to(quiet, verbose, std::io::stderr);
}

/// [`init_cli_logging`] writing through `writer` instead of straight to stderr (bootstrap's
/// lines go above its status line).
pub fn init_cli_logging_to<W>(quiet: bool, verbose: u8, writer: W)
where
    W: for<'w> tracing_subscriber::fmt::MakeWriter<'w> + Send + Sync + 'static,
{
    let default = match (quiet, verbose) {
        (true, _) => "warn",
        (false, 0) => "info",
        (false, 1) => "debug",
        (false, _) => "trace",
    };
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new(default));
    // Err only if a subscriber is already set, which is what "harmless" above means.
    let _ = tracing_subscriber::fmt()
        .with_writer(writer)
        .with_env_filter(filter)
        .with_target(false)
        .with_ansi(std::io::stderr().is_terminal())
        .try_init();
}

/// The default full format, after a `[name pid N]` prefix.
struct Prefixed {
    /// `None` under a voter, which prefixes the lines itself.
    prefix: Option<String>,
    inner: Format<Full>,
}

impl<S, N> FormatEvent<S, N> for Prefixed
where
    S: Subscriber + for<'a> LookupSpan<'a>,
    N: for<'a> FormatFields<'a> + 'static,
{
    fn format_event(
        &self,
        ctx: &FmtContext<'_, S, N>,
        mut writer: Writer<'_>,
        event: &Event<'_>,
    ) -> fmt::Result {
        // The pid is read per line, not cached: after a restart by fork it is the child's.
        if let Some(prefix) = &self.prefix {
            write!(writer, "[{prefix} pid {}] ", std::process::id())?;
        }
        self.inner.format_event(ctx, writer, event)
    }
}

/// An error and its causes on one line, `what: why: because`, leaving out a cause whose text
/// the message before it already ends with (thiserror messages often quote their source).
pub fn error_chain(e: &(dyn std::error::Error + 'static)) -> String {
    let mut line = e.to_string();
    let mut cause = e.source();
    while let Some(c) = cause {
        let text = c.to_string();
        if !line.ends_with(&text) {
            line.push_str(": ");
            line.push_str(&text);
        }
        cause = c.source();
    }
    line
}

#[cfg(test)]
mod tests {
    use super::{component_filter, error_chain, prefix_lines};
    use tracing::Level;

    #[test]
    fn a_components_filter_takes_levels_and_targets_and_defaults_to_info() {
        let info = component_filter(None);
        assert!(info.would_enable("s3res_echo", &Level::INFO));
        assert!(!info.would_enable("s3res_echo", &Level::DEBUG));
        // What bootstrap passes on for -q and -v.
        let warn = component_filter(Some("warn"));
        assert!(warn.would_enable("replica_rt", &Level::WARN));
        assert!(!warn.would_enable("replica_rt", &Level::INFO));
        assert!(component_filter(Some("trace")).would_enable("replica_rt", &Level::TRACE));
        // Per target.
        let mixed = component_filter(Some("warn,replica_rt=debug"));
        assert!(mixed.would_enable("replica_rt::port", &Level::DEBUG));
        assert!(!mixed.would_enable("s3res_echo", &Level::INFO));
        // Empty directives are skipped, and so is one that does not read; the rest stands.
        for v in [
            "warn,",
            ",warn",
            "warn,,",
            "foo[{x=1}]=debug,warn",
            "warn,replica_rt=loud",
        ] {
            let f = component_filter(Some(v));
            assert!(f.would_enable("s3res_echo", &Level::WARN), "{v}");
            assert!(!f.would_enable("s3res_echo", &Level::INFO), "{v}");
        }
        // Nothing that reads: the default.
        for bad in ["replica_rt=loud", "a=b=c", "", " , "] {
            let f = component_filter(Some(bad));
            assert!(f.would_enable("s3res_echo", &Level::INFO), "{bad}");
            assert!(!f.would_enable("s3res_echo", &Level::DEBUG), "{bad}");
        }
    }

    #[test]
    fn every_line_is_prefixed_and_ends() {
        assert_eq!(
            prefix_lines("[echo#1 pid 7] ", "panicked: boom\n  at x.rs:1"),
            "[echo#1 pid 7] panicked: boom\n[echo#1 pid 7]   at x.rs:1\n"
        );
    }

    #[derive(Debug, thiserror::Error)]
    #[error("cannot create {path}: {source}")]
    struct Quoting {
        path: &'static str,
        source: std::io::Error,
    }

    #[test]
    fn a_quoted_cause_is_not_repeated() {
        let io = std::io::Error::new(std::io::ErrorKind::NotFound, "no such file");
        let e = anyhow::Error::new(Quoting {
            path: "x",
            source: io,
        })
        .context("did not run");
        assert_eq!(
            error_chain(e.as_ref()),
            "did not run: cannot create x: no such file"
        );
        let plain = anyhow::anyhow!("inner").context("outer");
        assert_eq!(error_chain(plain.as_ref()), "outer: inner");
    }
}
