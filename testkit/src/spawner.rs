//! Starting a process that dies with the test process, however the test process dies.
//!
//! A test's drop guards kill what it started when the test ends, passes or fails; they do not
//! run when the test process itself is killed (Ctrl-C on `cargo test`, a CI time limit's
//! SIGKILL). For that, each bootstrap gets `PR_SET_PDEATHSIG` SIGKILL, and a SIGKILLed
//! bootstrap ends everything it started (`tests/supervision.rs`). The kernel sends that signal
//! when the *thread* that forked the child exits, not the process, and a test runs on a thread
//! of its own that ends with the test; so the children are forked by one thread that lives as
//! long as the process, and a test thread hands it the command and gets the child back.

use std::io;
use std::process::{Child, Command};
use std::sync::mpsc;
use std::sync::OnceLock;

type Request = (Command, mpsc::SyncSender<io::Result<Child>>);

/// The spawning thread's queue; never dropped, so the thread never ends before the process.
static SPAWNER: OnceLock<mpsc::Sender<Request>> = OnceLock::new();

/// Spawns `cmd` so that its process gets SIGKILL when the test process dies. For anything a
/// test starts that could outlive it: a bootstrap (`System::start` uses it), an injector or a
/// benchmark that starts systems of its own.
pub fn spawn_tied_to_this_process(mut cmd: Command) -> io::Result<Child> {
    replica_rt::sys::die_with_parent(&mut cmd, libc::SIGKILL);
    let spawner = SPAWNER.get_or_init(|| {
        let (tx, rx) = mpsc::channel::<Request>();
        std::thread::Builder::new()
            .name("s3res-testkit-spawner".into())
            .spawn(move || {
                for (mut cmd, reply) in rx {
                    // The requester blocks on the answer until it comes.
                    let _ = reply.send(cmd.spawn());
                }
            })
            .expect("starting the testkit's spawning thread");
        tx
    });
    let (reply, answer) = mpsc::sync_channel(1);
    spawner
        .send((cmd, reply))
        .map_err(|_| io::Error::other("the testkit's spawning thread is gone"))?;
    answer
        .recv()
        .map_err(|_| io::Error::other("the testkit's spawning thread did not answer"))?
}
