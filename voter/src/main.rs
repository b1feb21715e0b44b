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
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            let unrecoverable = e
                .downcast_ref::<VoterError>()
                .is_some_and(|v| matches!(v, VoterError::Unrecoverable(_)));
            // One write: replicas and unprotected components share this stderr, and a line
            // written in pieces could be interleaved with theirs.
            let line = format!("s3res-voter: {e:#}\n");
            let _ = std::io::Write::write_all(&mut std::io::stderr().lock(), line.as_bytes());
            std::process::ExitCode::from(if unrecoverable { 3 } else { 1 })
        }
    }
}

fn run() -> anyhow::Result<()> {
    let cli = Cli::parse();
    let plan = VoterPlan::from_json(&cli.plan).context("reading --plan")?;
    let span = tracing::info_span!("voter", component = %plan.component);
    let _enter = span.enter();
    match plan.mode {
        Mode::Reactive => ReactiveVoter::start(plan)?.run()?,
        Mode::Stream => StreamVoter::start(plan)?.run()?,
    }
    Ok(())
}
