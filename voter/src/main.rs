//! `s3res-voter`: started by `s3res-bootstrap`, never by hand.

use anyhow::Context;
use clap::Parser;
use s3res_voter::plan::{Mode, VoterPlan};
use s3res_voter::{ReactiveVoter, StreamVoter, VoterError};

/// The voter of one protected s3res component.
///
/// s3res-bootstrap starts one voter per protected component (redundancy smr, dmr or tmr) and
/// hands it the component's pipes as inherited fds, described by the plan. The voter starts the
/// replicas, copies every input frame to each, votes on their answers byte for byte, forwards
/// the majority, and replaces crashed, hung, corrupted or misbehaving replicas by forking a
/// healthy one. Events (faults, recoveries) go as JSON lines to the plan's events fd.
///
/// Two modes: reactive (a round per input frame, one answer per output) and stream (the k-th
/// frame of each output is voted across replicas; see docs/stream-mode.md).
///
/// Exit status: 0 when the inputs closed and the replicas finished, or on SIGTERM/SIGINT;
/// 1 on a start-up error; 3 when the component failed beyond recovery.
#[derive(Parser, Debug)]
#[command(version, verbatim_doc_comment)]
struct Cli {
    /// The voter plan as JSON (s3res_voter::plan::VoterPlan), written by s3res-bootstrap.
    #[arg(long)]
    plan: String,
}

fn main() -> std::process::ExitCode {
    replica_rt::init_cli_logging(false, 0);
    match run() {
        Ok(component) => match s3res_voter::stray_stop() {
            None => std::process::ExitCode::SUCCESS,
            // Stopped by someone else than bootstrap: this component ends alone, and its
            // neighbours will starve or choke on it. Say who, and end as killed by it would.
            Some(stop) => {
                let by = replica_rt::sys::command_name(stop.from)
                    .map(|name| format!(" ({name})"))
                    .unwrap_or_default();
                say(&format!(
                    "component {component} stopped: its voter got signal {} from pid {}{by}, \
                     not from bootstrap",
                    stop.signal, stop.from
                ));
                std::process::ExitCode::from(128 + stop.signal as u8)
            }
        },
        Err(e) => {
            let unrecoverable = e
                .downcast_ref::<VoterError>()
                .is_some_and(|v| matches!(v, VoterError::Unrecoverable(_)));
            say(&format!("{e:#}"));
            std::process::ExitCode::from(if unrecoverable { 3 } else { 1 })
        }
    }
}

/// One line on stderr behind `s3res-voter: `, in one write: replicas and unprotected
/// components share this stderr, and a line written in pieces could be interleaved with
/// theirs.
fn say(what: &str) {
    let line = format!("s3res-voter: {what}\n");
    let _ = std::io::Write::write_all(&mut std::io::stderr().lock(), line.as_bytes());
}

/// Runs the voter of the plan on the command line to its end; the component's name.
fn run() -> anyhow::Result<String> {
    let cli = Cli::parse();
    let plan = VoterPlan::from_json(&cli.plan).context("reading --plan")?;
    let component = plan.component.clone();
    let span = tracing::info_span!("voter", component = %plan.component);
    let _enter = span.enter();
    match plan.mode {
        Mode::Reactive => ReactiveVoter::start(plan)?.run()?,
        Mode::Stream => StreamVoter::start(plan)?.run()?,
    }
    Ok(component)
}
