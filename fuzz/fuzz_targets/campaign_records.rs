//! The campaign readers `s3res-inject merge` uses: `campaign.json`, `runs.jsonl` and
//! `injections.jsonl` (`CampaignOutput::parse`, what `CampaignOutput::read` does with a
//! folder's files), then the merge, the summary with its confidence intervals, and the tables.
//! The input is the three texts separated by NUL bytes. Nothing may panic; a summary's counts
//! add up and every interval holds its rate.
#![no_main]

use libfuzzer_sys::fuzz_target;
use s3res_inject::report::{markdown, merge, CampaignOutput};

fuzz_target!(|data: &[u8]| {
    let mut parts = data.splitn(3, |&b| b == 0);
    let mut next = || String::from_utf8_lossy(parts.next().unwrap_or_default()).into_owned();
    let texts = [next(), next(), next()];
    let labels = ["campaign.json", "runs.jsonl", "injections.jsonl"].map(str::to_owned);
    let Ok(out) = CampaignOutput::parse(labels, texts.each_ref()) else {
        return;
    };
    // A campaign merged with itself repeats its runs: refused, unless it has none.
    let twice = merge(vec![out.clone(), out.clone()]);
    assert_eq!(twice.is_ok(), out.runs.is_empty(), "{twice:?}");
    let merged = merge(vec![out]).expect("one campaign merges");
    let summaries: Vec<_> = merged.iter().map(CampaignOutput::summary).collect();
    for s in &summaries {
        assert_eq!(s.injected + s.missed, s.planned);
        assert!(s.after_end <= s.missed, "{s:?}");
        assert!(s.successful_runs <= s.runs_done);
        for r in [s.error_rate, s.success_rate].into_iter().flatten() {
            assert!(r.holds(), "{r:?}");
        }
        let _ = serde_json::to_string(s).unwrap();
    }
    let _ = markdown(&summaries);
});
