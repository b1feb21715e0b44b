//! Logging set-up of the command-line tools: one function for the whole project, in replica-rt.

pub use replica_rt::init_cli_logging;

/// bootstrap's own logging: [`init_cli_logging`], its lines printed above the status line when
/// one is shown.
pub fn init_status_logging(quiet: bool, verbose: u8) {
    replica_rt::init_cli_logging_to(quiet, verbose, crate::status::StatusAwareStderr);
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
    use super::error_chain;

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
