// Newcomer mistakes, one mode per run: s3res-newbie MODE [N]
use anyhow::{bail, Context, Result};
use std::hash::{BuildHasher, Hasher};

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let mode = args.get(1).cloned().unwrap_or_else(|| "ok".into());
    let n: u64 = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(5);
    replica_rt::init_logging("newbie");
    let mut rt = replica_rt::init().context("starting the s3res runtime")?;
    let mut input = rt.input("in").context("opening port `in`")?;
    let mut out = rt.output("out").context("opening port `out`")?;

    // worker thread (mode thread-worker): main hands each value to it and waits for the result
    let (to_w, w_rx) = std::sync::mpsc::channel::<u64>();
    let (w_tx, from_w) = std::sync::mpsc::channel::<u64>();
    if mode == "thread" {
        std::thread::spawn(|| loop { std::thread::sleep(std::time::Duration::from_secs(1)); });
    }
    if mode == "thread-worker" {
        std::thread::spawn(move || { while let Ok(v) = w_rx.recv() { let _ = w_tx.send(v * 2); } });
    }
    let mut count = 0u64;
    let mut sum = 0u64;
    let mut leaked: Vec<Vec<u8>> = Vec::new();
    while let Some(frame) = input.recv().context("receiving")? {
        let v = if frame.len() >= 4 { u32::from_le_bytes(frame[..4].try_into().unwrap()) as u64 } else { 0 };
        count += 1;
        sum += v;
        let mut ans = Vec::with_capacity(24);
        ans.extend_from_slice(&count.to_le_bytes());
        ans.extend_from_slice(&sum.to_le_bytes());
        match mode.as_str() {
            "ts" => { let t = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_nanos() as u64; ans.extend_from_slice(&t.to_le_bytes()); }
            "rand" => { let mut h = std::collections::hash_map::RandomState::new().build_hasher(); h.write_u64(count); ans.extend_from_slice(&h.finish().to_le_bytes()); }
            "println" => { println!("debug: got {v}, count {count}"); }
            "println-only" => { println!("{count} {sum}"); continue; }
            "slow" => { std::thread::sleep(std::time::Duration::from_millis(n)); }
            "thread-worker" => { to_w.send(v).unwrap(); let r = from_w.recv().unwrap(); ans.extend_from_slice(&r.to_le_bytes()); }
            "alloc" => { let mut b = vec![0u8; (n as usize) << 20]; for i in (0..b.len()).step_by(4096) { b[i] = count as u8; } ans.push(b[4096]); }
            "leak" => { let mut b = vec![0u8; (n as usize) << 20]; for i in (0..b.len()).step_by(4096) { b[i] = 1; } leaked.push(b); }
            "exit" => { if count == n { bail!("simulated failure at frame {count}"); } }
            "exit-one" => { if count == n && rt.replica_index() == Some(1) { bail!("simulated failure at frame {count}"); } }
            "nofirst" => { if count == 1 { continue; } }
            "never" => { continue; }
            "two" => { out.send(&ans).context("send")?; }
            "two-at" => { if count == n { out.send(&ans).context("send")?; } }
            "panic" => { if count == n { panic!("simulated bug at frame {count}"); } }
            _ => {}
        }
        out.send(&ans).context("sending")?;
    }
    tracing::info!(count, "end of input");
    Ok(())
}
