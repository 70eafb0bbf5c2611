//! Synthetic recorded sessions for the pipeline tests: static scans of a box room by eq. (1)'s
//! geometry (ranges ray-cast against the room's walls) and RPLidar revolutions, written with the
//! real recorder. Every static-scan message is built in [`SessionBuilder::static_scan`], so a
//! protocol change touches one place.
#![allow(dead_code)]

use std::path::{Path, PathBuf};

use scan3d_map::cloud::assembly::{MountGeometry, Position, sensor_origin};
use scan3d_protocol::{
    Body, Frame, LidarRevolution, MountInfo, SensorId, StaticScan, StaticScanEnd,
    StaticScanOutcome, StaticScanStart, StaticScanYaws, YawRun, encode,
};
use scan3d_server::recording::{SessionRecorder, session_dir};

/// The default room: an axis-aligned box, metres.
pub const ROOM: ([f64; 3], [f64; 3]) = ([0.0, 0.0, 0.0], [4.0, 3.0, 2.5]);

/// The simulator's conference room's size (the demo's maps), metres.
pub const DEMO_ROOM: ([f64; 3], [f64; 3]) = ([0.0, 0.0, 0.0], [8.0, 6.0, 3.0]);

/// The mount every synthetic static scan uses.
pub const MOUNT: MountGeometry = MountGeometry {
    axis_offset_m: 0.05,
    height_m: 1.0,
    azimuth_zero_deg: 0.0,
};

/// Distance from `o` along the unit vector `d` to the walls of `room` (from inside).
pub fn range_to_walls(room: ([f64; 3], [f64; 3]), o: [f64; 3], d: [f64; 3]) -> f64 {
    let (lo, hi) = room;
    (0..3)
        .filter(|&a| d[a].abs() > 1e-12)
        .map(|a| {
            let wall = if d[a] > 0.0 { hi[a] } else { lo[a] };
            (wall - o[a]) / d[a]
        })
        .fold(f64::INFINITY, f64::min)
}

/// One thing to record.
#[derive(Debug, Clone)]
pub enum Recorded {
    /// A decodable frame.
    Frame(Frame),
    /// A frame the server could not decode, under this edge seq.
    Undecodable(u64),
}

/// Builds a session's frames in sequence order.
#[derive(Debug)]
pub struct SessionBuilder {
    pub session_id: u64,
    seq: u64,
    t_ns: u64,
    scan_id: u32,
    room: ([f64; 3], [f64; 3]),
    pub items: Vec<Recorded>,
}

impl SessionBuilder {
    /// An empty session in [`ROOM`].
    pub fn new(session_id: u64) -> Self {
        Self::in_room(session_id, ROOM)
    }

    /// An empty session in `room` (min and max corner).
    pub fn in_room(session_id: u64, room: ([f64; 3], [f64; 3])) -> Self {
        SessionBuilder {
            session_id,
            seq: 0,
            t_ns: 1_000_000_000,
            scan_id: 0,
            room,
            items: Vec::new(),
        }
    }

    /// The edge time the next frame starts at, ns.
    pub fn now_ns(&self) -> u64 {
        self.t_ns
    }

    /// Appends any frame body (e.g. a pass marker) with the next sequence number.
    pub fn push(&mut self, body: impl Into<Body>) {
        self.items
            .push(Recorded::Frame(Frame::new(self.session_id, self.seq, body)));
        self.seq += 1;
    }

    /// Leaves out the next `n` sequence numbers (a gap).
    pub fn skip_seqs(&mut self, n: u64) {
        self.seq += n;
    }

    /// An undecodable frame.
    pub fn undecodable(&mut self) {
        self.items.push(Recorded::Undecodable(self.seq));
        self.seq += 1;
    }

    /// `n` RPLidar revolutions of `samples` samples each, seen from (2, 1.5, 0.2), heading 0.
    pub fn rplidar_revolutions(&mut self, n: usize, samples: usize) {
        for _ in 0..n {
            let mut rev =
                LidarRevolution::new(SensorId::RPLIDAR, self.t_ns, self.t_ns + 100_000_000);
            for i in 0..samples {
                let angle = 360.0 * i as f64 / samples as f64;
                // RPLidar angles are clockwise.
                let a = (-angle).to_radians();
                let r = range_to_walls(self.room, [2.0, 1.5, 0.2], [a.cos(), a.sin(), 0.0]);
                let range = if i % 17 == 0 { 0.0 } else { r as f32 };
                rev.push(
                    angle as f32,
                    range,
                    40,
                    self.t_ns + (i as u64) * 100_000_000 / samples as u64,
                )
                .expect("sample time");
            }
            self.t_ns += 100_000_000;
            self.push(rev);
        }
    }

    /// `n` RPLidar revolutions of `samples` samples each from a lidar 0.2 m up that starts at
    /// `start` (x, y, heading in rad) and moves at constant `velocity` (m/s along x and y of the
    /// room, rad/s): each sample is ray-cast from where the lidar is at that sample's time.
    /// Returns the true pose (x, y, heading) at the middle of each revolution's samples, the
    /// time the mapper gives a revolution's pose.
    pub fn rplidar_moving(
        &mut self,
        n: usize,
        samples: usize,
        start: [f64; 3],
        velocity: [f64; 3],
    ) -> Vec<[f64; 3]> {
        let t_start = self.t_ns;
        let pose_at = |t_ns: u64| {
            let t = (t_ns - t_start) as f64 * 1e-9;
            [
                start[0] + velocity[0] * t,
                start[1] + velocity[1] * t,
                start[2] + velocity[2] * t,
            ]
        };
        let mut middles = Vec::with_capacity(n);
        for _ in 0..n {
            let t1 = self.t_ns + 180_000_000;
            let last = self.t_ns + (samples as u64 - 1) * 180_000_000 / samples as u64;
            middles.push(pose_at(self.t_ns + (last - self.t_ns) / 2));
            let mut rev = LidarRevolution::new(SensorId::RPLIDAR, self.t_ns, t1);
            for i in 0..samples {
                let t = self.t_ns + (i as u64) * 180_000_000 / samples as u64;
                let [x, y, heading] = pose_at(t);
                let angle = 360.0 * i as f64 / samples as f64;
                // RPLidar angles are clockwise.
                let a = heading + (-angle).to_radians();
                let r = range_to_walls(self.room, [x, y, 0.2], [a.cos(), a.sin(), 0.0]);
                rev.push(angle as f32, r as f32, 40, t)
                    .expect("sample time");
            }
            self.t_ns = t1;
            self.push(rev);
        }
        middles
    }

    /// A static scan at `position`: `revolutions` Sweep revolutions of `samples` samples, the
    /// turntable stepping `180 / revolutions` degrees in each blocked sector (θ in (150°, 210°)
    /// is blocked); every sample's range ray-cast against the room.
    pub fn static_scan(&mut self, position: &Position, revolutions: u32, samples: u32) {
        let scan_id = self.scan_id;
        self.scan_id += 1;
        let step = 180.0 / f64::from(revolutions);
        self.push(StaticScan::Started(StaticScanStart {
            scan_id,
            t_ns: self.t_ns,
            position: position.name.clone(),
            x_m: position.x_m,
            y_m: position.y_m,
            heading_deg: position.heading_deg,
            step_deg: step,
            total_deg: 180.0,
            blocked_sector_deg: 60.0,
            mount: MountInfo {
                axis_offset_m: MOUNT.axis_offset_m,
                height_m: MOUNT.height_m,
                azimuth_zero_deg: MOUNT.azimuth_zero_deg,
            },
        }));
        let mut tagged_total = 0u64;
        for r in 0..revolutions {
            let t0 = self.t_ns;
            let mut sweep = LidarRevolution::new(SensorId::SWEEP, t0, t0 + 200_000_000);
            let mut runs: Vec<YawRun> = Vec::new();
            for i in 0..samples {
                let azimuth = 360.0 * f64::from(i) / f64::from(samples);
                let t = t0 + u64::from(i) * 200_000_000 / u64::from(samples);
                let yaw = if azimuth < 180.0 {
                    step * f64::from(r)
                } else {
                    step * f64::from(r + 1)
                };
                let theta = (azimuth - MOUNT.azimuth_zero_deg).to_radians();
                let phi = (position.heading_deg + yaw).to_radians();
                let o = sensor_origin(position, &MOUNT, yaw);
                let d = [
                    -theta.sin() * phi.sin(),
                    theta.sin() * phi.cos(),
                    theta.cos(),
                ];
                let range = if i % 23 == 5 {
                    0.0
                } else {
                    range_to_walls(self.room, o, d) as f32
                };
                sweep
                    .push(azimuth as f32, range, 90, t)
                    .expect("sample time");
                if (150.0..=210.0).contains(&azimuth) {
                    continue;
                }
                tagged_total += 1;
                match runs.last_mut() {
                    Some(run) if run.yaw_deg == yaw as f32 && run.first_index + run.count == i => {
                        run.count += 1;
                    }
                    _ => runs.push(YawRun {
                        first_index: i,
                        count: 1,
                        yaw_deg: yaw as f32,
                    }),
                }
            }
            self.push(sweep);
            self.push(StaticScan::Yaws(StaticScanYaws {
                scan_id,
                revolution_t0_ns: t0,
                runs,
            }));
            self.t_ns += 200_000_000;
        }
        self.push(StaticScan::Finished(StaticScanEnd {
            scan_id,
            t_ns: self.t_ns,
            outcome: StaticScanOutcome::Completed,
            yaw_deg: 180.0,
            revolutions,
            tagged: tagged_total,
            blocked: 0,
            untrusted: 0,
            late_steps: 0,
            failed_steps: 0,
        }));
    }

    /// The decodable frames, in order.
    pub fn frames(&self) -> impl Iterator<Item = &Frame> {
        self.items.iter().filter_map(|i| match i {
            Recorded::Frame(f) => Some(f),
            Recorded::Undecodable(_) => None,
        })
    }

    /// Records the session under `data_dir` (edge `edge`) with the real recorder; returns the
    /// session directory.
    pub fn record(&self, data_dir: &Path, edge: &str) -> PathBuf {
        let mut rec =
            SessionRecorder::open(data_dir, edge, self.session_id).expect("open recorder");
        for (n, item) in self.items.iter().enumerate() {
            let log_time = 1_000 + n as u64;
            match item {
                Recorded::Frame(frame) => {
                    rec.append(&encode(frame).expect("encode"), frame, log_time)
                        .expect("append");
                }
                Recorded::Undecodable(seq) => {
                    rec.append_undecodable(
                        *seq,
                        b"S3DP\x02\x00\x03\x00\x00\x00\x2a\x00\x00",
                        "unknown body tag 42",
                        log_time,
                    )
                    .expect("append undecodable");
                }
            }
            if n % 64 == 63 {
                rec.commit().expect("commit");
            }
        }
        rec.commit().expect("commit");
        rec.close().expect("close");
        session_dir(data_dir, edge, self.session_id)
    }
}

/// A named position.
pub fn position(name: &str, x_m: f64, y_m: f64, heading_deg: f64) -> Position {
    Position {
        name: name.into(),
        x_m,
        y_m,
        heading_deg,
    }
}

/// Flips one bit in the middle of chunk `index` of the MCAP file `file`, which breaks that
/// chunk's CRC (the recording reader then skips it as damaged). Returns how many chunks the
/// file has.
pub fn break_chunk(file: &Path, index: usize) -> usize {
    let mut bytes = std::fs::read(file).expect("read the MCAP file");
    let chunks = chunk_bodies(&bytes);
    let (start, len) = *chunks
        .get(index)
        .unwrap_or_else(|| panic!("chunk {index} of {}", chunks.len()));
    bytes[start + len / 2] ^= 0x10;
    std::fs::write(file, &bytes).expect("write the MCAP file");
    chunks.len()
}

/// `(offset, length)` of every MCAP chunk record's body in `file` (records: opcode, u64 LE
/// length, body; after the 8-byte magic).
fn chunk_bodies(file: &[u8]) -> Vec<(usize, usize)> {
    let mut chunks = Vec::new();
    let mut at = 8;
    while at + 9 <= file.len() {
        let op = file[at];
        let len = u64::from_le_bytes(file[at + 1..at + 9].try_into().unwrap()) as usize;
        if op == 0x06 {
            chunks.push((at + 9, len));
        }
        at += 9 + len;
    }
    chunks
}
