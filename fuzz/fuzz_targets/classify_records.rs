//! The classification readers `s3res-inject merge` and `classify --resume` use:
//! `classify-run.json` and `classify.jsonl` (`ClassifyOutput::parse`, what
//! `ClassifyOutput::read` does with a folder's files) and the golden output, then the merge of
//! shards, the summary with its confidence intervals, and the table. The input is the two texts
//! and the golden bytes separated by NUL bytes. Nothing may panic; a summary's counts add up
//! and every interval holds its rate.
#![no_main]

use libfuzzer_sys::fuzz_target;
use s3res_inject::classify::{markdown, merge, ClassifyOutput};

fuzz_target!(|data: &[u8]| {
    let mut parts = data.splitn(3, |&b| b == 0);
    let mut next = || String::from_utf8_lossy(parts.next().unwrap_or_default()).into_owned();
    let texts = [next(), next()];
    let golden = parts.next().unwrap_or_default().to_vec();
    let labels = ["classify-run.json", "classify.jsonl"].map(str::to_owned);
    let Ok(out) = ClassifyOutput::parse(labels, texts.each_ref(), golden) else {
        return;
    };
    let dir = std::path::PathBuf::from("shard");
    // Records of other runs are left out; a run recorded twice is refused, and so is a folder
    // merged with itself, unless none of its records is one of its runs.
    let mut runs: Vec<u64> = out.records.iter().map(|r| r.run).collect();
    runs.retain(|&r| out.info.has_run(r));
    let kept = runs.len();
    runs.sort_unstable();
    runs.dedup();
    let unique = runs.len() == kept;
    assert!(out.info.run_count() >= runs.len() as u64);
    let twice = merge(vec![(dir.clone(), out.clone()), (dir.clone(), out.clone())]);
    assert_eq!(twice.is_ok(), kept == 0, "{twice:?}");
    let once = merge(vec![(dir, out)]);
    assert_eq!(once.is_ok(), unique, "{once:?}");
    let Ok(merged) = once else {
        return;
    };
    assert_eq!(merged.output.records.len(), kept);
    assert_eq!(merged.missing, merged.output.info.run_count() - kept as u64);
    let s = merged.output.summary();
    assert_eq!(
        s.benign + s.sdc + s.crash + s.hang + s.missed,
        s.runs,
        "{s:?}"
    );
    assert_eq!(s.classified + s.missed, s.runs);
    let rates = [s.rates.benign, s.rates.sdc, s.rates.crash, s.rates.hang];
    let missions = s.missions.as_ref().and_then(|m| m.successful);
    for r in rates.into_iter().chain([missions]).flatten() {
        assert!(r.holds(), "{r:?}");
    }
    let _ = serde_json::to_string(&s).unwrap();
    let _ = markdown(&[s]);
});
