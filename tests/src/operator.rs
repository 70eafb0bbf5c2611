//! The operator's flow off the Pi with the workspace's real binaries: `scan3d pair`, `scan3d
//! serve` on a free loopback port, `scan3d-sim rig` (the emulated sensor head), and the real
//! `scan3d-edge` daemon on the rig's `edge.toml` with the operator's `device_name`, `state_dir`
//! and `[uplink]`, after `check-config` accepted it.
//!
//! Shared by the rig's end-to-end test (`tests/rig_e2e.rs`, debug binaries) and the edge
//! daemon's CPU benchmark (`benches/edge_daemon.rs`, release binaries): the binaries are the
//! ones of the profile the caller was built with, found beside its executable.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

/// The directory holding the workspace's binaries of the caller's profile (target/<profile>/).
pub fn bin_dir() -> PathBuf {
    let exe = std::env::current_exe().expect("executable path");
    // target/<profile>/deps/NAME-HASH → target/<profile>
    exe.parent()
        .and_then(Path::parent)
        .expect("executable under target/<profile>/deps")
        .to_path_buf()
}

/// Whether the caller runs from target/release (a bench), so binaries are built `--release`.
fn release_profile() -> bool {
    bin_dir().file_name().is_some_and(|name| name == "release")
}

/// Builds `packages`' binaries in the caller's profile through `$CARGO` (a no-op when they
/// are up to date), so a benchmark never measures a stale binary.
pub fn build_binaries(packages: &[&str]) {
    let cargo = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
    let mut command = Command::new(cargo);
    command.arg("build").arg("--bins");
    if release_profile() {
        command.arg("--release");
    }
    for package in packages {
        command.args(["-p", package]);
    }
    let status = command.status().expect("run cargo build");
    assert!(status.success(), "cargo build of {packages:?} failed");
}

/// Path of a workspace binary, built through `$CARGO` when it is not there yet.
pub fn binary(name: &str, package: &str) -> PathBuf {
    let path = bin_dir().join(name);
    if !path.exists() {
        build_binaries(&[package]);
    }
    assert!(
        path.exists(),
        "{} not found after building it",
        path.display()
    );
    path
}

/// A child process killed when it is dropped, whatever happens.
pub struct Daemon(pub Child);

impl Daemon {
    /// The process id.
    pub fn pid(&self) -> u32 {
        self.0.id()
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Starts `program` at `RUST_LOG=info`, stderr to `log`, stdout piped.
pub fn spawn(program: &Path, args: &[&str], log: &Path) -> Daemon {
    let log = std::fs::File::create(log).expect("log file");
    Daemon(
        Command::new(program)
            .args(args)
            .env("RUST_LOG", "info")
            .stdout(Stdio::piped())
            .stderr(log)
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start {}: {e}", program.display())),
    )
}

/// Runs `program` to its end and returns what it printed.
pub fn run(program: &Path, args: &[&str]) -> Output {
    Command::new(program)
        .args(args)
        .output()
        .unwrap_or_else(|e| panic!("cannot run {}: {e}", program.display()))
}

/// Bytes as text, lossily.
pub fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

/// Waits until `ready` holds, polling every 200 ms; panics with `what` after `deadline`.
pub fn wait_until(what: &str, deadline: Duration, mut ready: impl FnMut() -> bool) {
    let start = Instant::now();
    while !ready() {
        assert!(start.elapsed() < deadline, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(200));
    }
}

/// The path as UTF-8 text (temporary directories are).
fn utf8(path: &Path) -> String {
    path.to_str().expect("utf-8 path").to_owned()
}

/// The rig, the server and the edge daemon running under `root`: the whole operator flow up to
/// a streaming edge. Every process is killed when this is dropped.
pub struct OperatorRig {
    root: PathBuf,
    /// The `scan3d` binary.
    pub scan3d: PathBuf,
    /// The server's `server.toml` (for `scan3d status --config`, `scan`, `snapshot`).
    pub server_toml: PathBuf,
    /// The edge's name, as paired.
    pub edge_name: String,
    // Dropped in this order: the edge first, then the server, then the rig.
    /// The `scan3d-edge` daemon.
    pub edge: Daemon,
    /// `scan3d serve`.
    pub server: Daemon,
    /// `scan3d-sim rig`.
    pub rig: Daemon,
}

impl OperatorRig {
    /// Starts the rig under `root/head`, pairs `edge_name` into `root/pki`, serves on a free
    /// loopback port (data in `root/data`), writes the operator's `root/edge.toml`, checks it
    /// with `scan3d-edge check-config` and starts the edge daemon. Logs go to
    /// `root/{rig,serve,edge}.log`.
    pub fn start(root: &Path, edge_name: &str) -> Self {
        Self::start_with_rig_args(root, edge_name, &[])
    }

    /// [`OperatorRig::start`] with more `scan3d-sim rig` options (`--trolley PATH.toml`).
    pub fn start_with_rig_args(root: &Path, edge_name: &str, rig_args: &[&str]) -> Self {
        let scan3d = binary("scan3d", "scan3d-server");
        let edge = binary("scan3d-edge", "scan3d-edge");
        let sim = binary("scan3d-sim", "scan3d-hw-sim");
        let p = |name: &str| root.join(name);

        // The head: it prints its four paths once they exist.
        let head = utf8(&p("head"));
        let mut args = vec!["rig", "--dir", head.as_str()];
        args.extend_from_slice(rig_args);
        let mut rig = spawn(&sim, &args, &p("rig.log"));
        let stdout = rig.0.stdout.take().expect("rig stdout");
        let printed: Vec<String> = BufReader::new(stdout)
            .lines()
            .take(4)
            .map(|l| l.expect("rig stdout line"))
            .collect();
        assert!(
            printed.iter().any(|l| l.ends_with("edge.toml")),
            "rig printed {printed:?}; log: {}",
            std::fs::read_to_string(p("rig.log")).unwrap_or_default()
        );

        // Pairing and the server on a free loopback port.
        let out = run(
            &scan3d,
            &["pair", "--dir", &utf8(&p("pki")), "--edge", edge_name],
        );
        assert!(out.status.success(), "pair: {}", text(&out.stderr));
        let port = std::net::UdpSocket::bind("127.0.0.1:0")
            .and_then(|socket| socket.local_addr())
            .expect("free port")
            .port();
        let server_toml = p("server.toml");
        std::fs::write(
            &server_toml,
            format!(
                "listen = \"127.0.0.1:{port}\"\npki_dir = \"{}\"\ndata_dir = \"{}\"\n",
                utf8(&p("pki")),
                utf8(&p("data"))
            ),
        )
        .expect("server.toml");
        let server = spawn(
            &scan3d,
            &["serve", "--config", &utf8(&server_toml)],
            &p("serve.log"),
        );

        // The operator's edge.toml: device_name and state_dir, the rig's sections, [uplink].
        let sections = std::fs::read_to_string(p("head/edge.toml")).expect("rig's edge.toml");
        let edge_toml = p("edge.toml");
        std::fs::write(
            &edge_toml,
            format!(
                "device_name = \"{edge_name}\"\nstate_dir = \"{}\"\n{sections}\n[uplink]\n\
                 server = \"127.0.0.1:{port}\"\nserver_name = \"localhost\"\npki_dir = \"{}\"\n",
                utf8(&p("edge-state")),
                utf8(&p(&format!("pki/edges/{edge_name}")))
            ),
        )
        .expect("edge.toml");
        let out = run(&edge, &["check-config", "--config", &utf8(&edge_toml)]);
        assert!(
            out.status.success(),
            "check-config refused the rig's edge.toml: {}",
            text(&out.stderr)
        );
        let edge = spawn(&edge, &["--config", &utf8(&edge_toml)], &p("edge.log"));
        Self {
            root: root.to_path_buf(),
            scan3d,
            server_toml,
            edge_name: edge_name.to_owned(),
            edge,
            server,
            rig,
        }
    }

    /// `scan3d ARGS --config server.toml`, run to its end.
    pub fn scan3d(&self, args: &[&str]) -> Output {
        let mut all: Vec<&str> = args.to_vec();
        let config = utf8(&self.server_toml);
        all.extend(["--config", &config]);
        run(&self.scan3d, &all)
    }

    /// The edge daemon's log so far.
    pub fn edge_log(&self) -> String {
        std::fs::read_to_string(self.root.join("edge.log")).unwrap_or_default()
    }

    /// A path under the root directory.
    pub fn path(&self, name: &str) -> PathBuf {
        self.root.join(name)
    }
}
