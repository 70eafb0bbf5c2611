//! Driver tests through the [`LidarDriver`] trait with a fake clock. Expected bytes are written
//! by hand from the research notes; data blocks come from an encoder written here from the layout.

use super::*;

const MS_NS: u64 = 1_000_000;

/// Encode one data block from the layout in research notes §2.4.
fn enc(sync: bool, err: bool, az: u16, cm: u16, strength: u8) -> [u8; 7] {
    let b0 = u8::from(sync) | (u8::from(err) << 1);
    let mut b = [
        b0,
        az as u8,
        (az >> 8) as u8,
        cm as u8,
        (cm >> 8) as u8,
        strength,
        0,
    ];
    b[6] = (b[..6].iter().map(|&x| u32::from(x)).sum::<u32>() % 255) as u8;
    b
}

fn writes(d: &mut Sweep) -> Vec<Transmit> {
    std::iter::from_fn(|| d.poll_transmit()).collect()
}

fn events(d: &mut Sweep) -> Vec<LidarEvent> {
    std::iter::from_fn(|| d.poll_event()).collect()
}

fn w(bytes: &[u8]) -> Transmit {
    Transmit::Write(bytes.to_vec())
}

fn samples(ev: &[LidarEvent]) -> Vec<ArrivedSample> {
    ev.iter()
        .filter_map(|e| match e {
            LidarEvent::Sample(s) => Some(*s),
            _ => None,
        })
        .collect()
}

fn warnings(ev: &[LidarEvent]) -> usize {
    ev.iter()
        .filter(|e| matches!(e, LidarEvent::Warning(_)))
        .count()
}

/// Fire the pending timer and return its deadline.
fn fire(d: &mut Sweep) -> u64 {
    let t = d.poll_timeout().expect("a timer is pending");
    d.handle_timeout(t);
    t
}

/// start → DX, 35 ms, flush, DX → `DX00P` → ID → IV → MI; returns the time, MI just sent.
fn up_to_mi(d: &mut Sweep) -> u64 {
    d.start(0);
    assert_eq!(writes(d), [w(b"DX\n")]);
    assert_eq!(d.poll_timeout(), Some(35 * MS_NS));
    // The answer to the first DX (and anything else) is ignored and flushed.
    d.handle_input(10 * MS_NS, b"DX00P\n");
    assert_eq!(fire(d), 35 * MS_NS);
    assert_eq!(writes(d), [Transmit::FlushInput, w(b"DX\n")]);
    let mut now = 40 * MS_NS;
    d.handle_input(now, b"DX00P\n");
    assert_eq!(writes(d), [w(b"ID\n")]);
    now += MS_NS;
    d.handle_input(now, b"ID115200110050500\n");
    assert_eq!(writes(d), [w(b"IV\n")]);
    now += MS_NS;
    d.handle_input(now, b"IVSWEEP01011100000001\n");
    assert_eq!(
        events(d),
        [LidarEvent::Info(DeviceInfo {
            model: "Sweep".into(),
            firmware: "1.1".into(),
            hardware: 1,
            serial: "00000001".into(),
        })]
    );
    assert_eq!(writes(d), [w(b"MI\n")]);
    now
}

/// A driver with default settings, streaming at 5 Hz / 500 Hz; returns it and the time.
fn streaming() -> (Sweep, u64) {
    let mut d = Sweep::new(SweepConfig::default()).unwrap();
    let mut now = up_to_mi(&mut d);
    now += MS_NS;
    d.handle_input(now, b"MI05\n");
    assert_eq!(writes(&mut d), [w(b"MZ\n")]);
    now += MS_NS;
    d.handle_input(now, b"MZ00\n");
    assert_eq!(writes(&mut d), [w(b"DS\n")]);
    now += MS_NS;
    d.handle_input(now, b"DS00P\n");
    assert_eq!(
        events(&mut d),
        [LidarEvent::Scanning {
            sample_period_ns: 2_000_000
        }]
    );
    assert!(d.is_scanning());
    (d, now)
}

#[test]
fn config_defaults_and_validation() {
    let c: SweepConfig = toml::from_str("motor_hz = 7").unwrap();
    assert_eq!(c.motor_hz, Some(7));
    assert_eq!(c.sample_rate_code, None);
    assert_eq!(c.settle_timeout_ms, 15_000);
    assert!(toml::from_str::<SweepConfig>("motor_speed = 7").is_err());
    let bad = |c: SweepConfig| Sweep::new(c).err();
    let mut c = SweepConfig {
        motor_hz: Some(11),
        ..SweepConfig::default()
    };
    assert_eq!(bad(c.clone()), Some(SweepConfigError::MotorHz(11)));
    c.motor_hz = Some(0);
    assert_eq!(bad(c.clone()), Some(SweepConfigError::MotorHz(0)));
    c.motor_hz = None;
    c.sample_rate_code = Some(4);
    assert_eq!(bad(c.clone()), Some(SweepConfigError::SampleRateCode(4)));
    c.sample_rate_code = Some(3);
    c.answer_timeout_ms = 0;
    assert_eq!(bad(c), Some(SweepConfigError::Zero("answer_timeout_ms")));
}

#[test]
fn full_handshake_with_ms_and_ds_settle_retries() {
    let mut d = Sweep::new(SweepConfig {
        motor_hz: Some(7),
        sample_rate_code: Some(2),
        ..SweepConfig::default()
    })
    .unwrap();
    assert_eq!(d.kind(), LidarKind::Sweep);
    let mut now = up_to_mi(&mut d);
    assert_eq!(d.device_status().map(|s| s.motor_hz), Some(5));
    now += MS_NS;
    d.handle_input(now, b"MI05\n");
    assert_eq!(writes(&mut d), [w(b"MS07\n")]);
    // MS answered 12: wait for MZ 00, then send MS again.
    now += MS_NS;
    d.handle_input(now, b"MS07\n12S\n");
    assert_eq!(warnings(&events(&mut d)), 1);
    assert_eq!(writes(&mut d), [w(b"MZ\n")]);
    now += MS_NS;
    d.handle_input(now, b"MZ01\n");
    assert!(writes(&mut d).is_empty());
    assert_eq!(d.poll_timeout(), Some(now + 500 * MS_NS));
    now = fire(&mut d);
    assert_eq!(writes(&mut d), [w(b"MZ\n")]);
    d.handle_input(now, b"MZ00\n");
    assert_eq!(writes(&mut d), [w(b"MS07\n")]);
    d.handle_input(now, b"MS07\n00P\n");
    assert_eq!(writes(&mut d), [w(b"LR02\n")]);
    d.handle_input(now, b"LR02\n00P\n");
    assert_eq!(writes(&mut d), [w(b"MZ\n")]);
    d.handle_input(now, b"MZ00\n");
    assert_eq!(writes(&mut d), [w(b"DS\n")]);
    // DS answered 12: warn, wait the retry interval, poll MZ, DS again.
    d.handle_input(now, b"DS12S\n");
    assert_eq!(warnings(&events(&mut d)), 1);
    assert!(writes(&mut d).is_empty());
    assert_eq!(d.poll_timeout(), Some(now + 1_000 * MS_NS));
    now = fire(&mut d);
    assert_eq!(writes(&mut d), [w(b"MZ\n")]);
    d.handle_input(now, b"MZ00\n");
    assert_eq!(writes(&mut d), [w(b"DS\n")]);
    // The receipt and the first blocks arrive in one read.
    let mut bytes = b"DS00P\n".to_vec();
    // Six blocks: the last one waits for its successor to confirm it.
    for i in 0..6u16 {
        bytes.extend_from_slice(&enc(i == 0, false, 10 + i * 100, 200 + i, 50));
    }
    now += MS_NS;
    d.handle_input(now, &bytes);
    let ev = events(&mut d);
    assert_eq!(
        ev[0],
        LidarEvent::Scanning {
            sample_period_ns: 1_333_333
        }
    );
    let s = samples(&ev);
    assert_eq!(s.len(), 5);
    assert_eq!(
        s[0],
        ArrivedSample {
            sample: RawSample {
                angle_deg: 10.0 / 16.0,
                range_m: 2.0,
                quality: 50,
                new_revolution: true
            },
            arrival_ns: now
        }
    );
    assert!(!s[4].sample.new_revolution);
    assert_eq!(s[4].sample.range_m, 2.04);
    assert_eq!((d.motor_hz(), d.sample_rate_hz()), (7, 750));
    assert_eq!(d.stats().samples_emitted, 5);
}

#[test]
fn ms_invalid_parameter_fails_with_a_device_error() {
    let mut d = Sweep::new(SweepConfig {
        motor_hz: Some(10),
        ..SweepConfig::default()
    })
    .unwrap();
    let now = up_to_mi(&mut d);
    d.handle_input(now, b"MI05\n");
    assert_eq!(writes(&mut d), [w(b"MS10\n")]);
    d.handle_input(now, b"MS10\n11R\n");
    let ev = events(&mut d);
    let [LidarEvent::Failed(DriverError::Device(msg))] = ev.as_slice() else {
        panic!("expected a device failure, got {ev:?}");
    };
    assert!(
        msg.contains("MS10") && msg.contains("invalid parameter"),
        "{msg}"
    );
    assert_eq!(d.poll_timeout(), None);
    assert!(writes(&mut d).is_empty());
}

#[test]
fn ds_motor_stopped_sets_ms05_and_retries() {
    let mut d = Sweep::new(SweepConfig::default()).unwrap();
    let now = up_to_mi(&mut d);
    d.handle_input(now, b"MI05\n");
    assert_eq!(writes(&mut d), [w(b"MZ\n")]);
    d.handle_input(now, b"MZ00\n");
    assert_eq!(writes(&mut d), [w(b"DS\n")]);
    d.handle_input(now, b"DS13T\n");
    assert_eq!(warnings(&events(&mut d)), 1);
    assert_eq!(writes(&mut d), [w(b"MS05\n")]);
    d.handle_input(now, b"MS05\n00P\n");
    assert_eq!(writes(&mut d), [w(b"MZ\n")]);
    d.handle_input(now, b"MZ00\n");
    assert_eq!(writes(&mut d), [w(b"DS\n")]);
    d.handle_input(now, b"DS00P\n");
    assert!(d.is_scanning());
}

#[test]
fn motor_at_zero_hz_gets_ms05() {
    let mut d = Sweep::new(SweepConfig::default()).unwrap();
    let now = up_to_mi(&mut d);
    d.handle_input(now, b"MI00\n");
    assert_eq!(writes(&mut d), [w(b"MS05\n")]);
}

#[test]
fn no_answer_to_dx_fails_after_three_attempts() {
    let mut d = Sweep::new(SweepConfig::default()).unwrap();
    d.start(0);
    fire(&mut d);
    assert_eq!(
        writes(&mut d),
        [w(b"DX\n"), Transmit::FlushInput, w(b"DX\n")]
    );
    assert_eq!(fire(&mut d), 1_035 * MS_NS);
    assert_eq!(writes(&mut d), [w(b"DX\n")]);
    fire(&mut d);
    assert_eq!(writes(&mut d), [w(b"DX\n")]);
    fire(&mut d);
    assert!(writes(&mut d).is_empty());
    let ev = events(&mut d);
    assert_eq!(warnings(&ev), 2);
    assert_eq!(
        ev.last(),
        Some(&LidarEvent::Failed(DriverError::NoAnswer {
            command: "DX",
            attempts: 3
        }))
    );
    assert_eq!(d.poll_timeout(), None);
}

#[test]
fn dx_receipt_is_found_after_in_flight_blocks_and_garbage() {
    let mut d = Sweep::new(SweepConfig::default()).unwrap();
    d.start(0);
    fire(&mut d);
    writes(&mut d);
    let mut bytes = Vec::new();
    for i in 0..20u16 {
        bytes.extend_from_slice(&enc(false, false, i * 50, 0x5844, 0x44)); // "DX" inside
    }
    bytes.extend_from_slice(b"DX0");
    d.handle_input(40 * MS_NS, &bytes);
    assert!(writes(&mut d).is_empty());
    d.handle_input(41 * MS_NS, b"0P\n");
    assert_eq!(writes(&mut d), [w(b"ID\n")]);
    assert!(samples(&events(&mut d)).is_empty());
    assert_eq!(d.stats().bytes_discarded, 140);
}

#[test]
fn wrong_receipt_sum_is_rejected() {
    let mut d = Sweep::new(SweepConfig::default()).unwrap();
    let now = up_to_mi(&mut d);
    d.handle_input(now, b"MI05\n");
    d.handle_input(now, b"MZ00\n");
    writes(&mut d);
    let before = d.stats().frames_rejected;
    d.handle_input(now, b"DS00Q\n");
    assert!(!d.is_scanning());
    assert_eq!(d.stats().frames_rejected, before + 1);
    d.handle_input(now, b"DS00P\n");
    assert!(d.is_scanning());
}

#[test]
fn settle_timeout_fails() {
    let mut d = Sweep::new(SweepConfig::default()).unwrap();
    let mut t = up_to_mi(&mut d);
    d.handle_input(t, b"MI05\n");
    let mut polls = 0;
    loop {
        assert_eq!(writes(&mut d), [w(b"MZ\n")]);
        polls += 1;
        d.handle_input(t, b"MZ01\n");
        if d.poll_timeout().is_none() {
            break;
        }
        t = fire(&mut d);
        assert!(polls < 100, "never gave up");
    }
    let ev = events(&mut d);
    assert!(
        matches!(ev.last(), Some(LidarEvent::Failed(DriverError::Device(m))) if m.contains("not stable")),
        "{ev:?}"
    );
    // Polls at 0, 0.5 s, …, 15 s: the one at the deadline gives up.
    assert_eq!(polls, 31);
}

#[test]
fn wrong_model_is_reported() {
    let mut d = Sweep::new(SweepConfig::default()).unwrap();
    d.start(0);
    fire(&mut d);
    d.handle_input(
        40 * MS_NS,
        b"DX00P\nID115200110050500\nIVLASER01011100000001\n",
    );
    let ev = events(&mut d);
    assert!(
        matches!(
            ev.last(),
            Some(LidarEvent::Failed(DriverError::WrongDevice(_)))
        ),
        "{ev:?}"
    );
}

#[test]
fn silence_while_scanning_restarts_the_handshake() {
    let (mut d, now) = streaming();
    let mut bytes = Vec::new();
    for i in 0..5u16 {
        bytes.extend_from_slice(&enc(false, false, i * 50, 100, 1));
    }
    let t = now + 100 * MS_NS;
    d.handle_input(t, &bytes);
    assert_eq!(d.poll_timeout(), Some(t + 2_000 * MS_NS));
    // Garbage is not data: it does not postpone the restart.
    d.handle_input(t + 1_000 * MS_NS, &[0xFF; 50]);
    assert_eq!(fire(&mut d), t + 2_000 * MS_NS);
    let ev = events(&mut d);
    assert_eq!(samples(&ev).len(), 4);
    assert_eq!(warnings(&ev), 1);
    assert_eq!(writes(&mut d), [w(b"DX\n")]);
    assert!(!d.is_scanning());
    assert_eq!(d.poll_timeout(), Some(t + 2_035 * MS_NS));
}

#[test]
fn stop_sends_dx_and_goes_idle_on_the_receipt() {
    let (mut d, now) = streaming();
    d.stop(now);
    assert_eq!(writes(&mut d), [w(b"DX\n")]);
    let mut bytes = enc(false, false, 10, 10, 10).to_vec();
    bytes.extend_from_slice(b"DX00P\n");
    d.handle_input(now + MS_NS, &bytes);
    assert_eq!(d.poll_timeout(), None);
    assert!(samples(&events(&mut d)).is_empty());
}

#[test]
fn error_blocks_are_counted_not_emitted_and_keep_their_sync() {
    let (mut d, now) = streaming();
    let mut bytes = Vec::new();
    for (sync, err, az) in [
        (false, false, 5600u16),
        (false, false, 5650),
        (false, false, 5700),
        (true, true, 20), // error block with the sync bit
        (false, false, 70),
        (false, false, 120),
        (false, false, 170), // confirms the previous block
    ] {
        bytes.extend_from_slice(&enc(sync, err, az, 300, 9));
    }
    d.handle_input(now, &bytes);
    let s = samples(&events(&mut d));
    let got: Vec<(f32, bool)> = s
        .iter()
        .map(|s| (s.sample.angle_deg, s.sample.new_revolution))
        .collect();
    assert_eq!(
        got,
        [
            (350.0, false),
            (353.125, false),
            (356.25, false),
            (4.375, true),
            (7.5, false)
        ]
    );
    assert_eq!(d.error_blocks(), 1);
}

#[test]
fn arrival_time_is_that_of_the_read_completing_each_block() {
    let (mut d, now) = streaming();
    let mut bytes = Vec::new();
    for i in 0..6u16 {
        bytes.extend_from_slice(&enc(false, false, 100 + i * 60, 0, 3));
    }
    // Reads end inside block 1 and inside block 4.
    d.handle_input(now + 1, &bytes[..10]);
    d.handle_input(now + 2, &bytes[10..30]);
    d.handle_input(now + 3, &bytes[30..]);
    let s = samples(&events(&mut d));
    let times: Vec<u64> = s.iter().map(|s| s.arrival_ns - now).collect();
    // The sixth block waits for its successor.
    assert_eq!(times, [1, 2, 2, 2, 3]);
    assert!(s.iter().all(|s| s.sample.range_m == 0.0));
}

/// xorshift64* — a small deterministic generator for the corruption test.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }

    fn unit(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }
}

#[derive(Clone, Copy)]
struct Orig {
    sync: bool,
    err: bool,
    az: u16,
    cm: u16,
    strength: u8,
    touched: bool,
}

#[test]
fn corrupted_stream_never_yields_foreign_samples() {
    let seeds: u64 = std::env::var("SWEEP_NOISE_SEEDS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(3);
    for seed in 0..seeds {
        corrupted_stream_run(0x9E37_79B9_7F4A_7C15 ^ seed.wrapping_mul(0x1000_0000_01B3));
    }
}

/// One run of the corruption test: stray bytes and bit flips at 1e-3 per byte each, at most
/// one per block.
fn corrupted_stream_run(seed: u64) {
    let (mut d, mut now) = streaming();
    let bytes_before = d.stats().bytes_in;
    let mut rng = Rng(seed);
    let n = 40_000u32;
    let mut orig = Vec::with_capacity(n as usize);
    let mut stream = Vec::new();
    let mut prev_az = 0u16;
    for i in 0..n {
        // 5 Hz at 500 Hz: 3.6° = 57.6 raw per sample.
        let az = ((u64::from(i) * 576 / 10) % 5760) as u16;
        let sync = i > 0 && az < prev_az;
        prev_az = az;
        let err = i % 97 == 13 && !sync;
        let cm = if i % 50 == 7 {
            0
        } else {
            (i * 7919 % 40_000) as u16
        };
        let strength = (i % 251) as u8;
        let mut touched = false;
        for byte in enc(sync, err, az, cm, strength) {
            // At most one corruption per block: two bit flips in one block can cancel in the
            // mod-255 sum (same bit, opposite directions), which no receiver can detect.
            let r = if touched { 1.0 } else { rng.unit() };
            if r < 1e-3 {
                stream.push(rng.next() as u8); // stray byte
                stream.push(byte);
                touched = true;
            } else if r < 2e-3 {
                stream.push(byte ^ (1 << (rng.next() % 8))); // bit flip
                touched = true;
            } else {
                stream.push(byte);
            }
        }
        orig.push(Orig {
            sync,
            err,
            az,
            cm,
            strength,
            touched,
        });
    }
    let mut rest = stream.as_slice();
    while !rest.is_empty() {
        let k = (1 + rng.next() % 200) as usize;
        let (chunk, tail) = rest.split_at(k.min(rest.len()));
        now += MS_NS;
        d.handle_input(now, chunk);
        rest = tail;
    }
    let ev = events(&mut d);
    assert_eq!(warnings(&ev), 0);
    let got = samples(&ev);
    // Every sample must match the stream's blocks in order (a subsequence of the non-error ones).
    let mut j = 0;
    let mut untouched_emitted = 0;
    for s in &got {
        let found = orig[j..].iter().position(|o| {
            !o.err
                && s.sample.angle_deg == f32::from(o.az) / 16.0
                && s.sample.range_m == f32::from(o.cm) / 100.0
                && s.sample.quality == o.strength
                && s.sample.new_revolution == o.sync
        });
        let Some(k) = found else {
            panic!("sample {s:?} was not in the stream (after block {j})");
        };
        j += k;
        if !orig[j].touched {
            untouched_emitted += 1;
        }
        j += 1;
    }
    let untouched = orig.iter().filter(|o| !o.touched && !o.err).count();
    let touched = orig.iter().filter(|o| o.touched).count();
    assert!(
        touched > 300,
        "corruption too rare to test anything: {touched}"
    );
    assert!(
        untouched_emitted * 100 >= untouched * 95,
        "{untouched_emitted} of {untouched} untouched blocks emitted"
    );
    let st = d.stats();
    assert_eq!(st.samples_emitted, got.len() as u64);
    assert_eq!(st.bytes_in - bytes_before, stream.len() as u64);
    assert!(st.resyncs > 0 && st.bytes_discarded > 0 && st.frames_rejected >= st.resyncs);
    let errors = orig.iter().filter(|o| o.err).count() as u64;
    let untouched_errors = orig.iter().filter(|o| o.err && !o.touched).count() as u64;
    assert!(d.error_blocks() <= errors && d.error_blocks() * 100 >= untouched_errors * 95);
    eprintln!(
        "{untouched_emitted}/{untouched} untouched emitted, {touched} touched, {} emitted, {st:?}",
        got.len()
    );
}

/// Parsing throughput; run with `cargo test --release -p scan3d-edge --lib sweep_throughput -- --ignored --nocapture`.
#[test]
#[ignore = "timing measurement"]
fn sweep_throughput() {
    let (mut d, now) = streaming();
    let mut stream = Vec::new();
    for i in 0..2_000_000u32 {
        let az = ((u64::from(i) * 576 / 10) % 5760) as u16;
        stream.extend_from_slice(&enc(az < 58 && i > 0, false, az, (i % 4000) as u16, 7));
    }
    let t0 = std::time::Instant::now();
    let mut n = 0usize;
    for (k, chunk) in stream.chunks(4096).enumerate() {
        d.handle_input(now + k as u64, chunk);
        while let Some(e) = d.poll_event() {
            n += usize::from(matches!(e, LidarEvent::Sample(_)));
        }
    }
    let secs = t0.elapsed().as_secs_f64();
    println!("{n} samples, {:.1} MB/s", stream.len() as f64 / secs / 1e6);
    assert_eq!(n, 2_000_000 - 1);
}
