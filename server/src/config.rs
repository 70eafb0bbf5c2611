//! The server daemon's configuration file (`server.toml`; example in `deploy/server.toml`).
//!
//! Every key is optional: an empty file gives [`ServerConfig::default`], which listens on
//! `[::]:4433` (dual stack: on Linux, with the default `net.ipv6.bindv6only = 0`, IPv4 edges reach
//! it too, as `::ffff:a.b.c.d`). On a host booted with IPv6 disabled, set `listen = "0.0.0.0:4433"`.

use std::net::{Ipv6Addr, SocketAddr};
use std::path::{Path, PathBuf};
use std::time::Duration;

use serde::{Deserialize, Deserializer};

use scan3d_map::cloud::filter::Filter;
use scan3d_map::octree::SensorModel;

use crate::ingest::server::IngestLimits;
use crate::pipeline::PipelineSettings;
use crate::pipeline::live::LiveSettings;

/// The whole `server.toml`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ServerConfig {
    /// UDP address the QUIC endpoint binds to.
    pub listen: SocketAddr,
    /// The directory given to `scan3d pair --dir`: the CA, the server certificate and key.
    pub pki_dir: PathBuf,
    /// Root of the recordings: sessions live in `data_dir/sessions/<edge>/<session-id>/`.
    pub data_dir: PathBuf,
    /// How often (ms) the recorder finishes a chunk, syncs it and acknowledges its frames. Bounds
    /// the acknowledgement latency; shorter means more, smaller chunks and more fsyncs.
    #[serde(deserialize_with = "positive_u64")]
    pub commit_interval_ms: u64,
    /// How often (ms) the server pings each edge for a time-sync exchange.
    #[serde(deserialize_with = "positive_u64")]
    pub time_sync_interval_ms: u64,
    /// The sliding window (s) of exchanges the clock model (offset and skew) is fitted over.
    #[serde(deserialize_with = "positive_u64")]
    pub time_sync_window_s: u64,
    /// The largest frequency error (ppm) of an edge clock against the server's that time sync
    /// estimates; a fitted skew is held within it.
    #[serde(deserialize_with = "skew_bound_ppm")]
    pub time_sync_max_skew_ppm: f64,
    /// Edges connected at once; further connections are refused.
    #[serde(deserialize_with = "positive_usize")]
    pub max_connections: usize,

    // What unauthenticated peers and each edge may cost (see `IngestLimits`).
    /// TLS handshakes in progress at once; further connection attempts are refused.
    #[serde(deserialize_with = "positive_usize")]
    pub max_handshakes: usize,
    /// With more handshakes than this in progress, peers must validate their address with a
    /// QUIC Retry first (0: always).
    pub retry_above_handshakes: usize,
    /// A TLS handshake not finished after this long (ms) is dropped.
    #[serde(deserialize_with = "positive_u64")]
    pub handshake_timeout_ms: u64,
    /// An authenticated edge that opens no stream within this long (ms) is disconnected.
    #[serde(deserialize_with = "positive_u64")]
    pub first_stream_timeout_ms: u64,
    /// Session recordings open at once per edge; the least recently used one is closed to
    /// open another.
    #[serde(deserialize_with = "positive_usize")]
    pub max_sessions_per_edge: usize,
    /// A session recording without frames for this long (ms) is closed.
    #[serde(deserialize_with = "positive_u64")]
    pub session_idle_timeout_ms: u64,
    /// Frame data (MiB, 1–4096) an edge may have waiting for a commit; more commits early.
    #[serde(deserialize_with = "buffer_mib")]
    pub max_buffered_mib_per_edge: u64,
    /// A new connection under a connected edge name replaces the old connection once that has
    /// received nothing for this long (ms); until then the new one is refused.
    #[serde(deserialize_with = "positive_u64")]
    pub replace_after_silence_ms: u64,

    /// The live mapping pipeline (`[pipeline]`).
    pub pipeline: PipelineSection,
}

/// `[pipeline]`: what the daemon builds from every session while it streams (see
/// `deploy/server.toml` for each key).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PipelineSection {
    /// Whether the daemon runs the pipeline at all (it always records).
    pub enabled: bool,
    /// Voxel edge length of the octrees, metres (0.001–10).
    #[serde(deserialize_with = "resolution")]
    pub resolution_m: f64,
    /// Rays longer than this are cut, metres; absent: no limit.
    #[serde(deserialize_with = "positive_f64")]
    pub max_range_m: Option<f64>,
    /// Per-revolution filters, `scan3d map --filter` syntax: `voxel:…`, `box:…`, `box-out:…`.
    #[serde(deserialize_with = "revolution_filters")]
    pub filters: Vec<Filter>,
    /// Filters applied to the whole cloud when a snapshot is written: `sor:…`, `gauss:…` (and
    /// any of the per-revolution ones).
    #[serde(deserialize_with = "any_filters")]
    pub snapshot_filters: Vec<Filter>,
    /// Hit probability of the octree insertion (OctoMap's 0.7).
    #[serde(deserialize_with = "probability")]
    pub hit: f64,
    /// Miss probability (OctoMap's 0.4).
    #[serde(deserialize_with = "probability")]
    pub miss: f64,
    /// Clamping probabilities `[min, max]` (OctoMap's 0.1192, 0.971).
    #[serde(deserialize_with = "clamp")]
    pub clamp: [f64; 2],
    /// A reference map (`.bt` / `.ot`, same resolution) the live metrics compare against.
    pub reference: Option<PathBuf>,
    /// Write every session's products into `data_dir/snapshots/<edge>/<session>/` this often,
    /// seconds; absent: only on request (`scan3d snapshot`).
    #[serde(deserialize_with = "positive_u64_opt")]
    pub snapshot_every_s: Option<u64>,
    /// Frames each session's processing queue holds (1–1048576); beyond, the pipeline catches
    /// up from the recording.
    #[serde(deserialize_with = "queue_frames")]
    pub queue_frames: usize,
    /// A sensor stream that falls this far (ms of edge time) behind the session's others is no
    /// longer waited for by the stages that merge them in sample-time order.
    #[serde(deserialize_with = "positive_u64")]
    pub lateness_ms: u64,
    /// A session's worker that has taken no frame for this long, seconds, writes its products
    /// to `data_dir/retired/<edge>/<session>/` and frees its maps (`status` and `snapshot`
    /// serve it from there; a later frame rebuilds it from the recording).
    #[serde(deserialize_with = "positive_u64")]
    pub retire_after_s: u64,
}

impl Default for PipelineSection {
    fn default() -> Self {
        let defaults = PipelineSettings::default();
        PipelineSection {
            enabled: true,
            resolution_m: defaults.resolution_m,
            max_range_m: None,
            filters: Vec::new(),
            snapshot_filters: Vec::new(),
            hit: 0.7,
            miss: 0.4,
            clamp: [0.1192, 0.971],
            reference: None,
            snapshot_every_s: None,
            queue_frames: 256,
            lateness_ms: defaults.lateness_ms,
            retire_after_s: 60,
        }
    }
}

impl PipelineSection {
    /// The pipeline's settings these keys give.
    pub fn settings(&self) -> PipelineSettings {
        PipelineSettings {
            resolution_m: self.resolution_m,
            max_range_m: self.max_range_m,
            sensor: SensorModel::from_probabilities(
                self.hit,
                self.miss,
                self.clamp[0],
                self.clamp[1],
                0.5,
            ),
            revolution_filters: self.filters.clone(),
            snapshot_filters: self.snapshot_filters.clone(),
            reference: self.reference.clone(),
            lateness_ms: self.lateness_ms,
        }
    }
}

/// Accepts a voxel size in metres from 1 mm to 10 m.
fn resolution<'de, D: Deserializer<'de>>(deserializer: D) -> Result<f64, D::Error> {
    let value = f64::deserialize(deserializer)?;
    if !(0.001..=10.0).contains(&value) {
        return Err(serde::de::Error::invalid_value(
            serde::de::Unexpected::Float(value),
            &"a resolution from 0.001 to 10 m",
        ));
    }
    Ok(value)
}

/// Accepts a positive, finite number of metres.
fn positive_f64<'de, D: Deserializer<'de>>(deserializer: D) -> Result<Option<f64>, D::Error> {
    let value = f64::deserialize(deserializer)?;
    if !(value.is_finite() && value > 0.0) {
        return Err(serde::de::Error::invalid_value(
            serde::de::Unexpected::Float(value),
            &"a positive number of metres",
        ));
    }
    Ok(Some(value))
}

/// Accepts a skew bound from 1 to 100 000 ppm (10 %: beyond any working clock).
fn skew_bound_ppm<'de, D: Deserializer<'de>>(deserializer: D) -> Result<f64, D::Error> {
    let value = f64::deserialize(deserializer)?;
    if !(1.0..=100_000.0).contains(&value) {
        return Err(serde::de::Error::invalid_value(
            serde::de::Unexpected::Float(value),
            &"a skew bound from 1 to 100000 ppm",
        ));
    }
    Ok(value)
}

/// Accepts a probability strictly between 0 and 1.
fn probability<'de, D: Deserializer<'de>>(deserializer: D) -> Result<f64, D::Error> {
    let value = f64::deserialize(deserializer)?;
    if !(value > 0.0 && value < 1.0) {
        return Err(serde::de::Error::invalid_value(
            serde::de::Unexpected::Float(value),
            &"a probability between 0 and 1 (exclusive)",
        ));
    }
    Ok(value)
}

/// Accepts `[min, max]`, two probabilities with min < max.
fn clamp<'de, D: Deserializer<'de>>(deserializer: D) -> Result<[f64; 2], D::Error> {
    let [lo, hi] = <[f64; 2]>::deserialize(deserializer)?;
    if !(lo > 0.0 && hi < 1.0 && lo < hi) {
        return Err(serde::de::Error::custom(format!(
            "clamp [{lo}, {hi}]: expected [min, max], probabilities with 0 < min < max < 1"
        )));
    }
    Ok([lo, hi])
}

/// Parses filters in `scan3d map --filter` syntax.
fn parse_filters<E: serde::de::Error>(texts: Vec<String>) -> Result<Vec<Filter>, E> {
    texts
        .iter()
        .map(|text| {
            text.parse::<Filter>()
                .map_err(|e| E::custom(format!("filter {text:?}: {e}")))
        })
        .collect()
}

/// Filters that work revolution by revolution (no neighbours across revolutions needed).
fn revolution_filters<'de, D: Deserializer<'de>>(deserializer: D) -> Result<Vec<Filter>, D::Error> {
    let texts = Vec::<String>::deserialize(deserializer)?;
    let filters = parse_filters(texts.clone())?;
    if let Some((text, _)) = texts
        .iter()
        .zip(&filters)
        .find(|(_, f)| matches!(f, Filter::Sor { .. } | Filter::Gauss { .. }))
    {
        return Err(serde::de::Error::custom(format!(
            "filter {text:?} needs neighbours across revolutions: put it in snapshot_filters"
        )));
    }
    Ok(filters)
}

fn any_filters<'de, D: Deserializer<'de>>(deserializer: D) -> Result<Vec<Filter>, D::Error> {
    parse_filters(Vec::<String>::deserialize(deserializer)?)
}

/// Rejects 0 (a period of 0 s would spin).
fn positive_u64_opt<'de, D: Deserializer<'de>>(deserializer: D) -> Result<Option<u64>, D::Error> {
    positive_u64(deserializer).map(Some)
}

/// The largest [`PipelineSection::queue_frames`].
const MAX_QUEUE_FRAMES: usize = 1 << 20;

fn queue_frames<'de, D: Deserializer<'de>>(deserializer: D) -> Result<usize, D::Error> {
    let value = usize::deserialize(deserializer)?;
    if value == 0 || value > MAX_QUEUE_FRAMES {
        return Err(serde::de::Error::invalid_value(
            serde::de::Unexpected::Unsigned(value as u64),
            &"a number of frames from 1 to 1048576",
        ));
    }
    Ok(value)
}

impl Default for ServerConfig {
    fn default() -> Self {
        Self {
            listen: SocketAddr::from((Ipv6Addr::UNSPECIFIED, 4433)),
            pki_dir: PathBuf::from("/etc/scan3d/pki"),
            data_dir: PathBuf::from("/var/lib/scan3d"),
            commit_interval_ms: 100,
            time_sync_interval_ms: 1000,
            time_sync_window_s: 120,
            time_sync_max_skew_ppm: 1000.0,
            max_connections: 16,
            max_handshakes: 64,
            retry_above_handshakes: 8,
            handshake_timeout_ms: 5000,
            first_stream_timeout_ms: 10_000,
            max_sessions_per_edge: 8,
            session_idle_timeout_ms: 60_000,
            max_buffered_mib_per_edge: 16,
            replace_after_silence_ms: 5000,
            pipeline: PipelineSection::default(),
        }
    }
}

/// The largest [`ServerConfig::max_buffered_mib_per_edge`]: 4 GiB, so `MiB << 20` cannot wrap.
const MAX_BUFFER_MIB: u64 = 4096;

/// Accepts 1..=[`MAX_BUFFER_MIB`].
fn buffer_mib<'de, D: Deserializer<'de>>(deserializer: D) -> Result<u64, D::Error> {
    let value = u64::deserialize(deserializer)?;
    if value == 0 || value > MAX_BUFFER_MIB {
        return Err(serde::de::Error::invalid_value(
            serde::de::Unexpected::Unsigned(value),
            &"a number of MiB from 1 to 4096",
        ));
    }
    Ok(value)
}

/// Rejects 0 (an interval of 0 ms would spin; the error carries the key's place in the file).
fn positive_u64<'de, D: Deserializer<'de>>(deserializer: D) -> Result<u64, D::Error> {
    let value = u64::deserialize(deserializer)?;
    if value == 0 {
        return Err(serde::de::Error::invalid_value(
            serde::de::Unexpected::Unsigned(0),
            &"a positive number",
        ));
    }
    Ok(value)
}

/// Rejects 0 (a server accepting no connection at all is a configuration mistake).
fn positive_usize<'de, D: Deserializer<'de>>(deserializer: D) -> Result<usize, D::Error> {
    let value = usize::deserialize(deserializer)?;
    if value == 0 {
        return Err(serde::de::Error::invalid_value(
            serde::de::Unexpected::Unsigned(0),
            &"a positive number",
        ));
    }
    Ok(value)
}

pub use scan3d_service::config::ConfigError;

impl ServerConfig {
    /// Parses a configuration from TOML text; `origin` names it in errors.
    pub fn from_toml_str(text: &str, origin: &Path) -> Result<Self, ConfigError> {
        scan3d_service::config::parse_toml(text, origin)
    }

    /// Reads and parses the configuration file at `path`.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        scan3d_service::config::load_toml(path)
    }

    /// [`commit_interval_ms`](Self::commit_interval_ms) as a [`Duration`].
    pub fn commit_interval(&self) -> Duration {
        Duration::from_millis(self.commit_interval_ms)
    }

    /// [`time_sync_interval_ms`](Self::time_sync_interval_ms) as a [`Duration`].
    pub fn time_sync_interval(&self) -> Duration {
        Duration::from_millis(self.time_sync_interval_ms)
    }

    /// [`time_sync_window_s`](Self::time_sync_window_s) as a [`Duration`].
    pub fn time_sync_window(&self) -> Duration {
        Duration::from_secs(self.time_sync_window_s)
    }

    /// The time-sync estimator's settings these keys give.
    pub fn time_sync(&self) -> crate::pose::timesync::TimeSyncConfig {
        crate::pose::timesync::TimeSyncConfig {
            max_skew_ppm: self.time_sync_max_skew_ppm,
            ..crate::pose::timesync::TimeSyncConfig::with_window(self.time_sync_window())
        }
    }

    /// The ingest limits these keys give.
    pub fn ingest_limits(&self) -> IngestLimits {
        IngestLimits {
            max_handshakes: self.max_handshakes,
            retry_above_handshakes: self.retry_above_handshakes,
            handshake_timeout: Duration::from_millis(self.handshake_timeout_ms),
            first_stream_timeout: Duration::from_millis(self.first_stream_timeout_ms),
            max_sessions_per_edge: self.max_sessions_per_edge,
            session_idle_timeout: Duration::from_millis(self.session_idle_timeout_ms),
            // At most 4096 MiB (checked when parsed), so this neither wraps nor truncates.
            max_buffered_bytes_per_edge: usize::try_from(self.max_buffered_mib_per_edge << 20)
                .unwrap_or(usize::MAX),
            replace_after_silence: Duration::from_millis(self.replace_after_silence_ms),
        }
    }

    /// The live driver's settings, or `None` with `[pipeline] enabled = false`.
    pub fn live_settings(&self) -> Option<LiveSettings> {
        let section = &self.pipeline;
        section.enabled.then(|| LiveSettings {
            queue_frames: section.queue_frames,
            snapshot_every: section.snapshot_every_s.map(Duration::from_secs),
            // Owed frames appear in the recording at the next commit.
            catch_up_retry: self.commit_interval().max(Duration::from_millis(10)),
            retire_after: Some(Duration::from_secs(section.retire_after_s)),
            ..LiveSettings::new(section.settings(), self.data_dir.clone())
        })
    }

    /// Where the recordings live: `data_dir/sessions`.
    pub fn sessions_dir(&self) -> PathBuf {
        self.data_dir.join("sessions")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<ServerConfig, ConfigError> {
        ServerConfig::from_toml_str(text, Path::new("server.toml"))
    }

    #[test]
    fn the_shipped_example_config_parses() {
        let path = Path::new(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../deploy/server.toml"
        ));
        let config = ServerConfig::load(path).expect("deploy/server.toml must parse");
        assert_eq!(config.listen, "[::]:4433".parse::<SocketAddr>().unwrap());
        assert_eq!(config.pki_dir, Path::new("/etc/scan3d/pki"));
        assert_eq!(config.data_dir, Path::new("/var/lib/scan3d"));
        assert_eq!(config.commit_interval_ms, 100);
        assert_eq!(config.time_sync_interval_ms, 1000);
        assert_eq!(config.max_connections, 16);
        assert_eq!(
            config,
            ServerConfig::default(),
            "the example shows the defaults"
        );
    }

    #[test]
    fn an_empty_file_gives_the_documented_defaults() {
        let config = parse("").unwrap();
        assert_eq!(config.listen.to_string(), "[::]:4433");
        assert_eq!(config.pki_dir, Path::new("/etc/scan3d/pki"));
        assert_eq!(config.data_dir, Path::new("/var/lib/scan3d"));
        assert_eq!(config.commit_interval(), Duration::from_millis(100));
        assert_eq!(config.time_sync_interval(), Duration::from_secs(1));
        assert_eq!(config.max_connections, 16);
        assert_eq!(config.sessions_dir(), Path::new("/var/lib/scan3d/sessions"));
        assert_eq!(config, ServerConfig::default());
    }

    #[test]
    fn every_key_is_read() {
        let text = "listen = \"127.0.0.1:5000\"\npki_dir = \"/tmp/pki\"\ndata_dir = \"/srv/d\"\n\
                    commit_interval_ms = 250\ntime_sync_interval_ms = 500\nmax_connections = 2\n";
        let config = parse(text).unwrap();
        assert_eq!(
            config,
            ServerConfig {
                listen: SocketAddr::from(([127, 0, 0, 1], 5000)),
                pki_dir: PathBuf::from("/tmp/pki"),
                data_dir: PathBuf::from("/srv/d"),
                commit_interval_ms: 250,
                time_sync_interval_ms: 500,
                max_connections: 2,
                ..ServerConfig::default()
            }
        );
    }

    #[test]
    fn the_default_ingest_limits_are_the_servers() {
        assert_eq!(
            ServerConfig::default().ingest_limits(),
            IngestLimits::default()
        );
    }

    #[test]
    fn every_ingest_limit_is_read() {
        let text = "max_handshakes = 10\nretry_above_handshakes = 0\nhandshake_timeout_ms = 700\n\
                    first_stream_timeout_ms = 800\nmax_sessions_per_edge = 3\n\
                    session_idle_timeout_ms = 900\nmax_buffered_mib_per_edge = 2\n\
                    replace_after_silence_ms = 1100\n";
        let limits = parse(text).unwrap().ingest_limits();
        assert_eq!(
            limits,
            IngestLimits {
                max_handshakes: 10,
                retry_above_handshakes: 0,
                handshake_timeout: Duration::from_millis(700),
                first_stream_timeout: Duration::from_millis(800),
                max_sessions_per_edge: 3,
                session_idle_timeout: Duration::from_millis(900),
                max_buffered_bytes_per_edge: 2 << 20,
                replace_after_silence: Duration::from_millis(1100),
            }
        );
    }

    #[test]
    fn zero_or_oversized_ingest_limits_are_refused_with_their_line() {
        for text in [
            "max_handshakes = 0",
            "handshake_timeout_ms = 0",
            "first_stream_timeout_ms = 0",
            "max_sessions_per_edge = 0",
            "session_idle_timeout_ms = 0",
            "max_buffered_mib_per_edge = 0",
            "max_buffered_mib_per_edge = 17592186044416",
            "replace_after_silence_ms = 0",
            "retry_above_handshakes = -1",
        ] {
            let message = parse(&format!("\n{text}\n")).unwrap_err().to_string();
            assert!(
                message.starts_with("server.toml: line 2:"),
                "{text}: {message}"
            );
        }
    }

    #[test]
    fn every_pipeline_key_is_read_and_converted_to_the_pipelines_settings() {
        let text = "data_dir = \"/d\"\n[pipeline]\nresolution_m = 0.1\nmax_range_m = 6.0\n\
                    filters = [\"voxel:0.02\", \"box:0,0,0,8,6,3\"]\n\
                    snapshot_filters = [\"sor:8,1.0\", \"gauss:0.02,0.05\"]\n\
                    hit = 0.8\nmiss = 0.3\nclamp = [0.2, 0.9]\nreference = \"/r/ref.bt\"\n\
                    snapshot_every_s = 30\nqueue_frames = 1\nretire_after_s = 5\n";
        let config = parse(text).unwrap();
        let settings = config.pipeline.settings();
        assert_eq!(settings.resolution_m, 0.1);
        assert_eq!(settings.max_range_m, Some(6.0));
        assert_eq!(
            settings.revolution_filters,
            vec![
                "voxel:0.02".parse().unwrap(),
                "box:0,0,0,8,6,3".parse().unwrap()
            ]
        );
        assert_eq!(settings.snapshot_filters.len(), 2);
        assert_eq!(
            settings.sensor,
            SensorModel::from_probabilities(0.8, 0.3, 0.2, 0.9, 0.5)
        );
        assert_eq!(settings.reference, Some(PathBuf::from("/r/ref.bt")));
        let live = config.live_settings().expect("enabled by default");
        assert_eq!(live.queue_frames, 1);
        assert_eq!(live.snapshot_every, Some(Duration::from_secs(30)));
        assert_eq!(live.retire_after, Some(Duration::from_secs(5)));
        assert_eq!(live.data_dir, Path::new("/d"));
        assert_eq!(live.pipeline, settings);
        let off = parse("[pipeline]\nenabled = false\n").unwrap();
        assert_eq!(off.live_settings(), None);
        // No [pipeline]: the defaults (on, 0.05 m, OctoMap's sensor model).
        let default = parse("").unwrap().pipeline.settings();
        assert_eq!(default, crate::pipeline::PipelineSettings::default());
    }

    #[test]
    fn bad_pipeline_keys_are_refused_with_their_line() {
        for (text, says) in [
            ("resolution_m = 0", "resolution"),
            ("resolution_m = 11.0", "resolution"),
            ("max_range_m = -1.0", "positive"),
            ("filters = [\"voxel:x\"]", "voxel:x"),
            ("filters = [\"sor:8,1.0\"]", "snapshot_filters"),
            ("snapshot_filters = [\"blur:1\"]", "blur:1"),
            ("hit = 1.0", "probability"),
            ("miss = 0", "probability"),
            ("clamp = [0.9, 0.2]", "min < max"),
            ("snapshot_every_s = 0", "positive"),
            ("retire_after_s = 0", "positive"),
            ("queue_frames = 0", "frames"),
            ("queue_frames = 2000000", "frames"),
            ("resolution = 0.05", "resolution"),
        ] {
            let message = parse(&format!("[pipeline]\n\n{text}\n"))
                .unwrap_err()
                .to_string();
            assert!(
                message.starts_with("server.toml: line 3:"),
                "{text}: {message}"
            );
            assert!(message.contains(says), "{text}: {message}");
        }
    }

    #[test]
    fn unknown_keys_are_reported_with_their_line() {
        let text = "listen = \"0.0.0.0:4433\"\n\ndatadir = \"/x\"\n";
        let message = parse(text).unwrap_err().to_string();
        assert!(message.starts_with("server.toml: line 3:"), "{message}");
        assert!(message.contains("datadir"), "{message}");
    }

    #[test]
    fn a_bad_address_is_reported_with_its_line() {
        let text = "# comment\nlisten = \"laptop:4433\"\n";
        let message = parse(text).unwrap_err().to_string();
        assert!(message.starts_with("server.toml: line 2:"), "{message}");
    }

    #[test]
    fn zero_intervals_and_limits_are_refused_with_their_line() {
        for (key, line) in [
            ("commit_interval_ms", 2),
            ("time_sync_interval_ms", 2),
            ("time_sync_window_s", 2),
            ("max_connections", 2),
        ] {
            let text = format!("data_dir = \"/d\"\n{key} = 0\n");
            let message = parse(&text).unwrap_err().to_string();
            assert!(
                message.starts_with(&format!("server.toml: line {line}:")),
                "{key}: {message}"
            );
            assert!(message.contains("positive"), "{key}: {message}");
        }
    }

    #[test]
    fn a_skew_bound_outside_1_to_100000_ppm_is_refused_with_its_line() {
        for value in ["0.5", "-200.0", "nan", "1e9"] {
            let text = format!("data_dir = \"/d\"\ntime_sync_max_skew_ppm = {value}\n");
            let message = parse(&text).unwrap_err().to_string();
            assert!(
                message.starts_with("server.toml: line 2:"),
                "{value}: {message}"
            );
            assert!(message.contains("skew bound"), "{value}: {message}");
        }
        let config = parse("time_sync_max_skew_ppm = 400.0\n").unwrap();
        assert_eq!(config.time_sync().max_skew_ppm, 400.0);
    }

    #[test]
    fn negative_and_mistyped_values_are_refused() {
        assert!(parse("commit_interval_ms = -5").is_err());
        assert!(parse("max_connections = \"16\"").is_err());
        assert!(parse("pki_dir = 3").is_err());
    }

    #[test]
    fn a_missing_file_names_the_path() {
        let path = Path::new("/nonexistent/scan3d/server.toml");
        let message = ServerConfig::load(path).unwrap_err().to_string();
        assert!(
            message.starts_with("cannot read /nonexistent/scan3d/server.toml:"),
            "{message}"
        );
    }
}
