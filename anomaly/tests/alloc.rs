//! `Detector::observe` (and the stream calls a voter makes on recovery) never allocate: counted
//! by a global allocator that tallies this thread's allocations.

use s3res_anomaly::network::Sgd;
use s3res_anomaly::synthetic::{flip, robot_layout, trainer_for, Robot};
use s3res_anomaly::{AutoencoderConfig, Detector, FloatRepr};
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

struct Counting;

thread_local! {
    static ALLOCATIONS: Cell<u64> = const { Cell::new(0) };
}

// SAFETY: every call is forwarded unchanged to the system allocator; the only addition is a
// thread-local counter with a const initialiser and no destructor, which does not allocate.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        ALLOCATIONS.with(|c| c.set(c.get() + 1));
        // SAFETY: the caller's contract for `alloc` is passed on as is.
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: `ptr` came from `System.alloc` above with this `layout`.
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        ALLOCATIONS.with(|c| c.set(c.get() + 1));
        // SAFETY: the caller's contract for `realloc` is passed on as is.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

fn allocations() -> u64 {
    ALLOCATIONS.with(Cell::get)
}

#[test]
fn observe_does_not_allocate() {
    // Control: the counter sees an allocation on this thread.
    let before = allocations();
    let boxed = std::hint::black_box(Box::new(7u64));
    assert_eq!(allocations(), before + 1, "the counting allocator counts");
    drop(boxed);

    let seed = 11;
    println!("seed {seed}");
    let layout = robot_layout();
    let frames = Robot::new(seed).frames(2_000);
    for floats in [FloatRepr::Value, FloatRepr::SignExponent] {
        let trainer = trainer_for([&frames[..1_000]], floats);
        let gaussian = trainer.gaussian(6.0, 1e-6).unwrap();
        let autoencoder = trainer
            .autoencoder(&AutoencoderConfig {
                seed,
                sgd: Sgd {
                    epochs: 2,
                    ..Sgd::default()
                },
                ..Default::default()
            })
            .unwrap();
        for model in [gaussian, autoencoder] {
            let mut detector = Detector::new(&model, 3).unwrap();
            let mut corrupted = frames[1_500];
            flip(&mut corrupted, &layout.fields()[3], 62);
            let mut nan = frames[1_501];
            nan[8..16].copy_from_slice(&f64::NAN.to_le_bytes());
            let mut alarms = 0;
            let before = allocations();
            for (k, f) in frames[1_000..].iter().enumerate() {
                for r in 0..3 {
                    alarms += u32::from(detector.observe(r, f).alarm);
                }
                if k % 100 == 50 {
                    alarms += u32::from(detector.observe(1, &corrupted).alarm);
                    alarms += u32::from(detector.observe(2, &nan).alarm);
                    alarms += u32::from(detector.observe(0, &f[..10]).alarm);
                    detector.copy_stream(0, 1);
                    detector.reset_stream(2);
                    detector.resync(2, f);
                }
            }
            let spent = allocations() - before;
            assert_eq!(
                spent,
                0,
                "{} allocations in observe ({:?})",
                spent,
                model.kind()
            );
            // The injected frames were really scored (and alarmed): the loop did the work.
            assert!(alarms >= 30, "{alarms} alarms");
        }
    }
}
