//! Shared pieces of the scan3d fuzz targets (fuzz/README.md):
//!
//! - [`Budget`], the global allocator of every target: it aborts, naming the sizes, as soon as
//!   the bytes live exceed what the current input justifies ([`with_budget`]). A reader that
//!   sizes an allocation from a hostile header is a finding even when the machine has the
//!   memory, so this is checked per input rather than left to libFuzzer's RSS limit.
//! - [`stream`], the session layout the lidar-driver targets read, and [`drive`], the loop that
//!   plays a session into a [`LidarDriver`] and checks what it promises.

pub mod stream;

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};

use scan3d_edge::lidar::{LidarDriver, LidarEvent, Transmit};

/// The system allocator, counting live bytes against the limit [`with_budget`] sets.
pub struct Budget;

static LIVE: AtomicUsize = AtomicUsize::new(0);
static LIMIT: AtomicUsize = AtomicUsize::new(usize::MAX);
/// Bytes live when the current budget started, and the input length, for the report.
static BASELINE: AtomicUsize = AtomicUsize::new(0);
static INPUT_LEN: AtomicUsize = AtomicUsize::new(0);

#[global_allocator]
static ALLOCATOR: Budget = Budget;

impl Budget {
    #[inline]
    fn charge(n: usize) {
        let live = LIVE.fetch_add(n, Ordering::Relaxed).saturating_add(n);
        if live > LIMIT.load(Ordering::Relaxed) {
            over_budget(live, n);
        }
    }
}

#[cold]
fn over_budget(live: usize, request: usize) -> ! {
    let limit = LIMIT.swap(usize::MAX, Ordering::Relaxed);
    // The limit is off now, so reporting may allocate.
    let base = BASELINE.load(Ordering::Relaxed);
    eprintln!(
        "scan3d-fuzz: allocation budget exceeded: a request of {request} bytes would make {} bytes \
         live, the budget for this {}-byte input is {} bytes",
        live.saturating_sub(base),
        INPUT_LEN.load(Ordering::Relaxed),
        limit.saturating_sub(base),
    );
    eprintln!("{}", std::backtrace::Backtrace::force_capture());
    // Never unwind out of an allocator: abort, which libFuzzer reports as a crash.
    std::process::abort()
}

// SAFETY: every method forwards to `System` with the caller's arguments; the counters are
// plain atomics and never affect the returned memory.
unsafe impl GlobalAlloc for Budget {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        Self::charge(layout.size());
        // SAFETY: forwarded unchanged.
        unsafe { System.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        Self::charge(layout.size());
        // SAFETY: forwarded unchanged.
        unsafe { System.alloc_zeroed(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        LIVE.fetch_sub(layout.size(), Ordering::Relaxed);
        // SAFETY: forwarded unchanged.
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if new_size > layout.size() {
            Self::charge(new_size - layout.size());
        } else {
            LIVE.fetch_sub(layout.size() - new_size, Ordering::Relaxed);
        }
        // SAFETY: forwarded unchanged.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

/// Runs `f` with at most `base + per_byte × input_len` bytes allocated beyond what was live
/// before; exceeding it aborts the process with the sizes and a backtrace.
pub fn with_budget<T>(input_len: usize, base: usize, per_byte: usize, f: impl FnOnce() -> T) -> T {
    lift_budget_on_panic();
    let baseline = LIVE.load(Ordering::Relaxed);
    BASELINE.store(baseline, Ordering::Relaxed);
    INPUT_LEN.store(input_len, Ordering::Relaxed);
    let budget = base.saturating_add(per_byte.saturating_mul(input_len));
    LIMIT.store(baseline.saturating_add(budget), Ordering::Relaxed);
    let out = f();
    LIMIT.store(usize::MAX, Ordering::Relaxed);
    out
}

/// Wraps the panic hook (libFuzzer's, installed before the first input) so that a panic under
/// a budget reports normally: formatting the message and the backtrace allocates.
fn lift_budget_on_panic() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        let report = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            LIMIT.store(usize::MAX, Ordering::Relaxed);
            report(info);
        }));
    });
}

/// Default budget of a reader target: 4 MiB plus 256 bytes per input byte.
pub fn with_reader_budget<T>(input_len: usize, f: impl FnOnce() -> T) -> T {
    with_budget(input_len, 4 << 20, 256, f)
}

/// How often [`LidarDriver::handle_timeout`] may be called at one instant before the driver
/// is declared stuck: its deadline must move past `now` (or go away) well before that.
const MAX_TIMEOUTS_PER_INSTANT: usize = 64;
/// Largest single write a driver may ask for (its longest request is a handful of bytes).
const MAX_WRITE: usize = 64;

/// Fires every timer due at `now`; panics if the deadline never moves past `now` (a serial
/// shell would spin on it).
fn fire_timers(driver: &mut dyn LidarDriver, now: u64) {
    for _ in 0..MAX_TIMEOUTS_PER_INSTANT {
        match driver.poll_timeout() {
            Some(deadline) if deadline <= now => driver.handle_timeout(now),
            _ => return,
        }
    }
    panic!(
        "timer livelock: deadline {:?} still due at {now} ns after {MAX_TIMEOUTS_PER_INSTANT} handle_timeout calls",
        driver.poll_timeout()
    );
}

/// Takes every transmit and event, checking each sample against the [`LidarEvent::Sample`]
/// contract: angle in `[0, 360)`, finite non-negative range, arrival not after `now` and not
/// before the previous sample's.
fn drain(driver: &mut dyn LidarDriver, now: u64, last_arrival: &mut u64, max_quality: u8) {
    while let Some(t) = driver.poll_transmit() {
        if let Transmit::Write(bytes) = t {
            assert!(
                bytes.len() <= MAX_WRITE,
                "a {}-byte write requested",
                bytes.len()
            );
        }
    }
    while let Some(event) = driver.poll_event() {
        if let LidarEvent::Sample(s) = event {
            let a = s.sample.angle_deg;
            assert!((0.0..360.0).contains(&a), "angle {a} outside [0, 360)");
            let r = s.sample.range_m;
            assert!(r.is_finite() && r >= 0.0, "range {r}");
            assert!(
                s.sample.quality <= max_quality,
                "quality {}",
                s.sample.quality
            );
            assert!(
                s.arrival_ns <= now,
                "arrival {} after now {now}",
                s.arrival_ns
            );
            assert!(
                s.arrival_ns >= *last_arrival,
                "arrival {} before the previous sample's {}",
                s.arrival_ns,
                *last_arrival
            );
            *last_arrival = s.arrival_ns;
        }
    }
}

/// Plays a session ([`stream::parse`]'s steps) into `driver` from [`LidarDriver::start`] at
/// time 0, as the serial shell does (timers, then the read, then transmits and events), with
/// `act` performing host actions. Checks the sample contract, that no timer livelocks, and
/// that [`scan3d_edge::lidar::DriverStats::bytes_in`] counts exactly the bytes fed.
pub fn drive<D: LidarDriver>(
    driver: &mut D,
    steps: &[stream::Step<'_>],
    max_quality: u8,
    mut act: impl FnMut(&mut D, u8, u64),
) {
    driver.start(0);
    let mut fed = 0u64;
    let mut last_arrival = 0u64;
    for step in steps {
        let now = match *step {
            stream::Step::Read { now_ns, bytes } => {
                fire_timers(driver, now_ns);
                driver.handle_input(now_ns, bytes);
                fed += bytes.len() as u64;
                now_ns
            }
            stream::Step::Action { now_ns, action } => {
                fire_timers(driver, now_ns);
                act(driver, action, now_ns);
                now_ns
            }
        };
        fire_timers(driver, now);
        drain(driver, now, &mut last_arrival, max_quality);
    }
    assert_eq!(driver.stats().bytes_in, fed, "bytes_in");
}

/// Offset of the data after an OctoMap header, found independently of the reader under test
/// (the same rules as `AbstractOcTree::readHeader`: the first line is the magic; then
/// whitespace-separated tokens, `id`/`size`/`res` take the next token, any other token skips its
/// line, and the data begins after the line of the `data` token). `None` without a `data` token.
pub fn octomap_data_offset(bytes: &[u8]) -> Option<usize> {
    let line_end = |from: usize| {
        bytes[from..]
            .iter()
            .position(|&b| b == b'\n')
            .map_or(bytes.len(), |i| from + i + 1)
    };
    let mut p = line_end(0);
    let token = |p: &mut usize| {
        while *p < bytes.len() && bytes[*p].is_ascii_whitespace() {
            *p += 1;
        }
        let start = *p;
        while *p < bytes.len() && !bytes[*p].is_ascii_whitespace() {
            *p += 1;
        }
        (start, *p)
    };
    loop {
        let (s, e) = token(&mut p);
        match &bytes[s..e] {
            b"" => return None,
            b"data" => return Some(line_end(p)),
            b"id" | b"size" | b"res" => {
                token(&mut p);
            }
            _ => p = line_end(p),
        }
    }
}

/// Checks what every tree read from a file must allow: leaf iteration agrees with the counts,
/// bounds and the max-likelihood `.bt` (OctoMap's `writeBinary`) are computable, equal to the
/// `.bt` of the explicitly pruned max-likelihood tree, and that `.bt` reads back to the same
/// bytes.
pub fn check_tree(tree: &scan3d_map::octree::Octree) {
    use scan3d_map::octree::Octree;
    assert_eq!(tree.leaves().count() as u64, tree.num_leaves());
    let _ = tree.metric_bounds();
    let bt = tree.to_bt_bytes();
    assert_eq!(
        bt,
        tree.to_max_likelihood_pruned().to_bt_bytes_const(),
        "the two-pass .bt writer differs from the pruned tree's .bt"
    );
    let again = Octree::read_bt(&bt, *tree.model()).expect("our own .bt must read back");
    assert_eq!(
        again.to_bt_bytes_const(),
        bt,
        ".bt write → read → write differs"
    );
}

/// The finite points of a flat cloud in file order, as `into_bundles` keeps them, bit for bit.
fn kept_points(cloud: scan3d_map::cloud::io::FlatCloud) -> Vec<[u32; 3]> {
    let scans = cloud
        .into_bundles(Some([0.0; 3]))
        .map(|loaded| loaded.bundles)
        .unwrap_or_default();
    scans
        .iter()
        .flat_map(|s| s.points.iter().map(|p| p.map(f32::to_bits)))
        .collect()
}

/// Cloud property for PLY and PCD: read → write (binary and ASCII) → read gives the same
/// points. `parse` reads a file, `write` writes scans in an encoding.
pub fn check_cloud_roundtrip<E: std::fmt::Debug>(
    cloud: scan3d_map::cloud::io::FlatCloud,
    parse: impl Fn(&[u8]) -> Result<scan3d_map::cloud::io::FlatCloud, E>,
    write: impl Fn(
        &mut Vec<u8>,
        &[scan3d_map::cloud::RayBundle],
        scan3d_map::cloud::io::Encoding,
    ),
) {
    use scan3d_map::cloud::io::Encoding;
    let scans = cloud
        .clone()
        .into_bundles(Some([0.0; 3]))
        .map(|loaded| loaded.bundles)
        .unwrap_or_default();
    let expected = kept_points(cloud);
    for encoding in [Encoding::Binary, Encoding::Ascii] {
        let mut out = Vec::new();
        write(&mut out, &scans, encoding);
        let back = parse(&out)
            .unwrap_or_else(|e| panic!("our own {encoding:?} file does not read back: {e:?}"));
        assert_eq!(
            kept_points(back),
            expected,
            "{encoding:?} read → write → read changed the points"
        );
    }
}
