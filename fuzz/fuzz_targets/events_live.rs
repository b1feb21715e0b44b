//! The readers of the voters' events and of bootstrap's live view: an event log line by line as
//! bootstrap reads it (`EventSummary::record_line`, then the live view's `apply` and the
//! status `Tally`), a state file as injectors read it (`LiveView`, then `target::resolve`).
//! The input is a state file, a NUL byte, then event lines. Nothing may panic; an event that
//! reads back writes the same event again; applying events never changes the shape of the
//! view nor makes it one a reader refuses; a target is the process the view names.
#![no_main]

use libfuzzer_sys::fuzz_target;
use s3res_bootstrap::events::{EventSummary, Line};
use s3res_bootstrap::status::Tally;
use s3res_inject::target::{resolve, Pick};
use s3res_protocol::event::Event;
use s3res_protocol::live::LiveView;

fuzz_target!(|data: &[u8]| {
    let (state, events) = match data.iter().position(|&b| b == 0) {
        Some(i) => (&data[..i], &data[i + 1..]),
        None => (data, &[][..]),
    };
    let mut view = LiveView::parse(&String::from_utf8_lossy(state)).ok();
    if let Some(v) = &view {
        let text = serde_json::to_string(v).unwrap();
        assert_eq!(&LiveView::parse(&text).unwrap(), v);
    }
    let shape = |v: &LiveView| -> Vec<(String, usize)> {
        v.components
            .iter()
            .map(|(name, c)| (name.clone(), c.replicas.len()))
            .collect()
    };
    let before = view.as_ref().map(shape);
    let mut summary = EventSummary::default();
    let tally = Tally::default();
    // As `events::read_all` reads the pipe: lines, lossily decoded.
    for line in events.split(|&b| b == b'\n') {
        let Line::Event(event) = summary.record_line(&String::from_utf8_lossy(line)) else {
            continue;
        };
        let again: Event = serde_json::from_str(&event.to_line()).expect("an event reads back");
        assert_eq!(again.to_line(), event.to_line());
        if let Some(v) = view.as_mut() {
            v.apply(&event);
        }
        tally.apply(&event);
    }
    let _ = summary.line();
    if let Some(v) = &view {
        assert_eq!(Some(shape(v)), before);
        // Whatever the events said, the view bootstrap would write reads back.
        v.check().expect("events keep the view readable");
        for (i, name) in v.components.keys().enumerate() {
            let draw = (i as f64 * 0.377).fract();
            if let Ok(t) = resolve(v, name, draw, Pick::Uniform) {
                // The target is the process the view names for its slot.
                let c = &v.components[name];
                let pid = match t.slot {
                    Some(slot) => c.replicas[slot].pid,
                    None => c.pid,
                };
                assert_eq!(Some(t.pid), pid);
            }
        }
    }
});
