//! Logging set-up, the one place of the project that installs a `tracing` subscriber: for
//! components ([`init_logging`]: each line prefixed with who wrote it) and for the command-line
//! tools and the voter ([`init_cli_logging`]: verbosity from `-q`/`-v`), and how they print an
//! error with its causes ([`error_chain`]).

use std::fmt::{self, Write as _};
use std::io::IsTerminal;
use std::sync::atomic::{AtomicU64, Ordering};

use tracing::field::{Field, Visit};
use tracing::span::{Attributes, Id, Record};
use tracing::{Event, Level, Metadata, Subscriber};
use tracing_subscriber::filter::{LevelFilter, Targets};
use tracing_subscriber::EnvFilter;

use crate::contract::{ENV_COMPONENT, ENV_REPLICA, ENV_STDERR_RELAYED, ENV_VOTER_SOCKET};

/// Installs a `tracing` subscriber that writes to stderr, filtered by `RUST_LOG` (default
/// `info`; bootstrap passes its `-q`/`-v` on through it: see [`component_filter`]), each line
/// prefixed with `[component#replica pid N]`, and a panic hook that prefixes a panic's lines
/// the same way.
///
/// The component name is `S3RES_COMPONENT`, or `component_default` when the process was not
/// started by s3res (by hand, in a shell pipeline). A replica (started by a voter) writes no
/// prefix: its stderr is a pipe of its own that the voter reads, and the voter writes each line
/// behind `[component#slot pid N]` (a fork child under its own slot); nor does an unprotected
/// component, whose stderr bootstrap relays the same way (`ENV_STDERR_RELAYED`). Calling it again is
/// harmless (the first subscriber stays).
pub fn init_logging(component_default: &str) {
    let component = std::env::var(ENV_COMPONENT).unwrap_or_else(|_| component_default.to_owned());
    // A replica's stderr is a pipe its voter reads: the voter puts `[component#slot pid N]`
    // before each line itself, from its own bookkeeping (a fork child's slot is not its
    // donor's), so the replica writes none.
    // An unprotected component's stderr is a pipe bootstrap reads, and bootstrap puts
    // `[component pid N]` before each line: the lines said it twice.
    let prefix = match std::env::var(ENV_REPLICA) {
        _ if std::env::var_os(ENV_VOTER_SOCKET).is_some() => None,
        _ if std::env::var_os(ENV_STDERR_RELAYED).is_some() => None,
        Ok(r) => Some(format!("{component}#{r}")),
        Err(_) => Some(component),
    };
    let filter = component_filter(std::env::var("RUST_LOG").ok().as_deref());
    install_panic_hook(prefix.clone());
    let log = ComponentLog::new(
        filter,
        prefix,
        std::io::stderr().is_terminal(),
        Box::new(|line| {
            let _ = std::io::Write::write_all(&mut std::io::stderr().lock(), line);
        }),
    );
    // Err only if a subscriber is already set, which is what "harmless" above means.
    if tracing::subscriber::set_global_default(log).is_ok() {
        // Records of the `log` crate (a dependency a component brings may use it) become
        // events too, up to the most verbose level the filter lets through.
        let _ = tracing_log::LogTracer::builder()
            .with_max_level(tracing_log::AsLog::as_log(&LevelFilter::current()))
            .init();
    }
}

/// Where a [`ComponentLog`] puts each whole line.
type LineSink = Box<dyn Fn(&[u8]) + Send + Sync>;

/// A component's `tracing` subscriber: each event that `filter` lets through becomes one line,
/// written whole with one call, in `tracing-subscriber`'s default format
/// (`2026-11-27T23:56:19.444536Z  WARN target: message key=value`, control characters in
/// messages and errors escaped), behind `[prefix pid N] ` when there is a prefix. On a
/// terminal it is coloured as `tracing-subscriber` colours it (a test compares the two).
///
/// Not `tracing-subscriber`'s registry and formatting layer, which the voter and the tools use:
/// the registry sets out 32 KiB of slots for 4,096 threads when it is made, which a replica
/// locks, keeps resident and copies at every fork recovery (8 pages; docs/results.md, "Fewer
/// pages to copy at a restart"). Components open no spans; this one keeps none, and shows an
/// event without the spans it is in.
pub struct ComponentLog {
    filter: Targets,
    most: LevelFilter,
    prefix: Option<String>,
    ansi: bool,
    sink: LineSink,
    next_span: AtomicU64,
}

/// The ANSI styles `tracing-subscriber` uses (through `nu-ansi-term`).
const DIM: &str = "\x1b[2m";
const ITALIC: &str = "\x1b[3m";
const RESET: &str = "\x1b[0m";

impl ComponentLog {
    pub fn new(filter: Targets, prefix: Option<String>, ansi: bool, sink: LineSink) -> Self {
        let most = filter
            .iter()
            .map(|(_, level)| level)
            .chain(filter.default_level())
            .max()
            .unwrap_or(LevelFilter::OFF);
        ComponentLog {
            filter,
            most,
            prefix,
            ansi,
            sink,
            next_span: AtomicU64::new(1),
        }
    }

    /// The line for `event`, newline included.
    fn line(&self, event: &Event<'_>) -> String {
        // A record of the `log` crate carries its own target and level in fields.
        let normalized = tracing_log::NormalizeEvent::normalized_metadata(event);
        let meta = normalized.as_ref().unwrap_or_else(|| event.metadata());
        let mut line = String::with_capacity(128);
        // The pid is read per line, not cached: after a restart by fork it is the child's.
        if let Some(prefix) = &self.prefix {
            let _ = write!(line, "[{prefix} pid {}] ", std::process::id());
        }
        let now = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap_or_default();
        let level = *meta.level();
        let target = meta.target();
        let _ = if self.ansi {
            let colour = match level {
                Level::ERROR => 31,
                Level::WARN => 33,
                Level::INFO => 32,
                Level::DEBUG => 34,
                Level::TRACE => 35,
            };
            write!(
                line,
                "{DIM}{}{RESET} \x1b[{colour}m{level:>5}{RESET} {DIM}{target}{RESET}{DIM}:{RESET} ",
                Utc(now)
            )
        } else {
            write!(line, "{} {level:>5} {target}: ", Utc(now))
        };
        event.record(&mut Fields {
            line: &mut line,
            empty: true,
            ansi: self.ansi,
        });
        line.push('\n');
        line
    }
}

impl Subscriber for ComponentLog {
    fn enabled(&self, meta: &Metadata<'_>) -> bool {
        self.filter.would_enable(meta.target(), meta.level())
    }

    fn max_level_hint(&self) -> Option<LevelFilter> {
        Some(self.most)
    }

    fn new_span(&self, _span: &Attributes<'_>) -> Id {
        Id::from_u64(self.next_span.fetch_add(1, Ordering::Relaxed))
    }

    fn record(&self, _span: &Id, _values: &Record<'_>) {}

    fn record_follows_from(&self, _span: &Id, _follows: &Id) {}

    fn event(&self, event: &Event<'_>) {
        (self.sink)(self.line(event).as_bytes());
    }

    fn enter(&self, _span: &Id) {}

    fn exit(&self, _span: &Id) {}
}

/// An event's fields as `tracing-subscriber` writes them: the message bare, then `name=value`
/// (`Debug`, so text is quoted), an error with its causes as `name.sources=[..]`.
struct Fields<'a> {
    line: &'a mut String,
    empty: bool,
    ansi: bool,
}

impl Fields<'_> {
    /// `text` in `style` on a terminal, plain otherwise.
    fn styled<'t>(&self, style: &'static str, text: &'t str) -> Styled<'t> {
        Styled(self.ansi.then_some(style), text)
    }
}

impl Visit for Fields<'_> {
    fn record_str(&mut self, field: &Field, value: &str) {
        if field.name() == "message" {
            self.record_debug(field, &format_args!("{value}"));
        } else {
            self.record_debug(field, &value);
        }
    }

    fn record_error(&mut self, field: &Field, value: &(dyn std::error::Error + 'static)) {
        match value.source() {
            Some(source) => self.record_debug(
                field,
                &format_args!(
                    "{} {}{}{}{}",
                    Escaped(value),
                    self.styled(ITALIC, field.name()),
                    self.styled(ITALIC, ".sources"),
                    self.styled(DIM, "="),
                    Sources(source)
                ),
            ),
            None => self.record_debug(field, &format_args!("{}", Escaped(value))),
        }
    }

    fn record_debug(&mut self, field: &Field, value: &dyn fmt::Debug) {
        let name = field.name();
        // What the `log` bridge adds (target, module, file, line): in the line's head already.
        if name.starts_with("log.") {
            return;
        }
        let pad = if self.empty { "" } else { " " };
        self.empty = false;
        let _ = if name == "message" {
            write!(self.line, "{pad}{}", Escaped(DebugAsDisplay(value)))
        } else {
            let name = name.strip_prefix("r#").unwrap_or(name);
            let (name, eq) = (self.styled(ITALIC, name), self.styled(DIM, "="));
            write!(self.line, "{pad}{name}{eq}{value:?}")
        };
    }
}

/// Text in an ANSI style, or plain (`None`).
struct Styled<'t>(Option<&'static str>, &'t str);

impl fmt::Display for Styled<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.0 {
            Some(style) => write!(f, "{style}{}{RESET}", self.1),
            None => f.write_str(self.1),
        }
    }
}

/// A `Debug` value written as its `Debug` text, for [`Escaped`].
struct DebugAsDisplay<'a>(&'a dyn fmt::Debug);

impl fmt::Display for DebugAsDisplay<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{:?}", self.0)
    }
}

/// Text with the control characters a terminal would act on written out as escapes (ESC,
/// BEL, BS, FF, DEL and the C1 controls), as `tracing-subscriber` writes messages and errors:
/// a log line cannot move the cursor, retitle the window or hide what came before.
struct Escaped<T>(T);

impl<T: fmt::Display> fmt::Display for Escaped<T> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        /// Escapes what passes through it on the way to `f`.
        struct Escaping<'a, 'b>(&'a mut fmt::Formatter<'b>);
        impl fmt::Write for Escaping<'_, '_> {
            fn write_str(&mut self, s: &str) -> fmt::Result {
                for ch in s.chars() {
                    match ch {
                        '\x1b' | '\x07' | '\x08' | '\x0c' | '\x7f' => {
                            write!(self.0, "\\x{:02x}", ch as u32)?
                        }
                        '\u{80}'..='\u{9f}' => write!(self.0, "\\u{{{:x}}}", ch as u32)?,
                        _ => self.0.write_char(ch)?,
                    }
                }
                Ok(())
            }
        }
        write!(Escaping(f), "{}", self.0)
    }
}

/// An error's causes, `[first, second]`, each escaped.
struct Sources<'a>(&'a (dyn std::error::Error + 'static));

impl fmt::Display for Sources<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let mut list = f.debug_list();
        let mut cause = Some(self.0);
        while let Some(c) = cause {
            list.entry(&format_args!("{}", Escaped(c)));
            cause = c.source();
        }
        list.finish()
    }
}

/// A time since the Unix epoch as `tracing-subscriber` prints it: RFC 3339, UTC, in µs.
struct Utc(std::time::Duration);

impl fmt::Display for Utc {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let secs = self.0.as_secs();
        let (days, of_day) = (secs / 86_400, secs % 86_400);
        // Days to a civil date (Howard Hinnant's `civil_from_days`), for days since 1970.
        let z = days as i64 + 719_468;
        let era = z.div_euclid(146_097);
        let doe = z.rem_euclid(146_097);
        let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
        let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
        let mp = (5 * doy + 2) / 153;
        let day = doy - (153 * mp + 2) / 5 + 1;
        let month = if mp < 10 { mp + 3 } else { mp - 9 };
        let year = yoe + era * 400 + i64::from(month <= 2);
        write!(
            f,
            "{year:04}-{month:02}-{day:02}T{:02}:{:02}:{:02}.{:06}Z",
            of_day / 3600,
            of_day / 60 % 60,
            of_day % 60,
            self.0.subsec_micros()
        )
    }
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
    use super::{component_filter, error_chain, prefix_lines, ComponentLog, Utc};
    use std::sync::{Arc, Mutex};
    use std::time::Duration;
    use tracing::Level;

    /// The lines a [`ComponentLog`] with `filter` and `prefix` writes while `f` runs.
    fn lines_of(rust_log: &str, prefix: Option<&str>, ansi: bool, f: impl FnOnce()) -> Vec<String> {
        let lines = Arc::new(Mutex::new(Vec::new()));
        let sink = Arc::clone(&lines);
        let log = ComponentLog::new(
            component_filter(Some(rust_log)),
            prefix.map(str::to_owned),
            ansi,
            Box::new(move |line| {
                sink.lock()
                    .unwrap()
                    .push(String::from_utf8(line.to_vec()).unwrap())
            }),
        );
        tracing::subscriber::with_default(log, f);
        let lines = lines.lock().unwrap().clone();
        lines
    }

    /// What tracing-subscriber's default format writes for the events of `f`, one line each.
    fn reference_lines(ansi: bool, f: impl FnOnce()) -> Vec<String> {
        #[derive(Clone, Default)]
        struct Capture(Arc<Mutex<Vec<u8>>>);
        impl std::io::Write for Capture {
            fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
                self.0.lock().unwrap().extend_from_slice(buf);
                Ok(buf.len())
            }
            fn flush(&mut self) -> std::io::Result<()> {
                Ok(())
            }
        }
        let capture = Capture::default();
        let out = capture.clone();
        let reference = tracing_subscriber::fmt()
            .with_writer(move || out.clone())
            .with_ansi(ansi)
            .with_max_level(Level::INFO)
            .finish();
        tracing::subscriber::with_default(reference, f);
        let text = String::from_utf8(capture.0.lock().unwrap().clone()).unwrap();
        text.lines().map(|l| format!("{l}\n")).collect()
    }

    /// A line without its time stamp (27 characters, plus the styling around it on a terminal).
    fn untimed(line: &str) -> String {
        let from = line.find("20").expect("a time stamp");
        let to = from + line[from..].find('Z').expect("the time stamp's end");
        format!("{}{}", &line[..from], &line[to + 1..])
    }

    #[derive(Debug, thiserror::Error)]
    #[error("outer\x1b[2J")]
    struct Outer(#[source] std::io::Error);

    /// Events of every kind of field.
    fn events() {
        tracing::warn!(count = 3, name = "x\x07", "end of input");
        tracing::debug!("not shown at info");
        let e = Outer(std::io::Error::other("inner\u{9b}"));
        tracing::error!(error = &e as &(dyn std::error::Error + 'static), "failed");
        let plain = std::io::Error::other("plain");
        tracing::info!(
            error = &plain as &(dyn std::error::Error + 'static),
            r#type = 1,
            "{} and {}",
            "formatted",
            2
        );
        tracing::info!(at = ?std::time::Duration::from_micros(1500), "a bell \x07, a clear \x1b[2J and a C1 \u{85}");
    }

    #[test]
    fn a_component_line_is_what_tracing_subscriber_writes() {
        for ansi in [false, true] {
            let ours = lines_of("info", None, ansi, events);
            let reference = reference_lines(ansi, events);
            assert_eq!(ours.len(), 4, "{ours:?}");
            let ours: Vec<String> = ours.iter().map(|l| untimed(l)).collect();
            let reference: Vec<String> = reference.iter().map(|l| untimed(l)).collect();
            assert_eq!(ours, reference, "ansi {ansi}");
        }
        // No raw control character reaches the line.
        for line in lines_of("info", None, false, events) {
            assert!(!line.trim_end().chars().any(|c| c.is_control()), "{line:?}");
        }
    }

    #[test]
    fn a_component_line_is_prefixed_and_filtered() {
        let lines = lines_of("info", Some("echo#1"), false, || {
            tracing::warn!(count = 3, "end of input");
            tracing::debug!("not shown at info");
        });
        let head = format!("[echo#1 pid {}] ", std::process::id());
        let rest = format!(" WARN {}: end of input count=3\n", module_path!());
        assert_eq!(lines.len(), 1, "{lines:?}");
        let stamp = lines[0]
            .strip_prefix(&head)
            .and_then(|l| l.strip_suffix(&rest))
            .unwrap_or_else(|| panic!("{:?} is not {head:?} <time> {rest:?}", lines[0]));
        // 2026-11-27T23:56:19.444536Z and the space after it.
        assert_eq!(stamp.len(), 28, "{stamp:?}");
        assert!(
            stamp.ends_with("Z ") && stamp.as_bytes()[10] == b'T',
            "{stamp:?}"
        );
        let debug = lines_of("warn,replica_rt=debug", None, false, || {
            tracing::debug!("shown")
        });
        assert!(
            debug[0].ends_with(&format!("DEBUG {}: shown\n", module_path!())),
            "{debug:?}"
        );
    }

    #[test]
    fn records_of_the_log_crate_are_lines_too() {
        let _ = tracing_log::LogTracer::builder()
            .with_max_level(log::LevelFilter::Trace)
            .init();
        let lines = lines_of("info", None, false, || {
            log::warn!(target: "some_crate::part", "from log {}", 1);
            log::debug!(target: "some_crate", "not shown at info");
        });
        assert_eq!(lines.len(), 1, "{lines:?}");
        assert!(
            lines[0].ends_with(" WARN some_crate::part: from log 1\n"),
            "{lines:?}"
        );
    }

    #[test]
    fn time_is_printed_as_rfc3339_utc_in_microseconds() {
        let at = |secs: u64, micros: u32| Utc(Duration::new(secs, micros * 1000)).to_string();
        assert_eq!(at(0, 0), "1970-01-01T00:00:00.000000Z");
        assert_eq!(at(951_782_400, 1), "2000-02-29T00:00:00.000001Z");
        assert_eq!(at(1_700_000_000, 123_456), "2023-11-14T22:13:20.123456Z");
        assert_eq!(at(1_798_761_599, 999_999), "2026-12-31T23:59:59.999999Z");
    }

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
