//! `scan3d serve` and the error line of the `scan3d` binary, run as a user would: a
//! `data_dir` that cannot be used, or whose control socket path is too long for a Unix socket,
//! stops the daemon at start with one line that names the path; a cause is printed once.

use std::path::Path;
use std::process::{Command, Output};

use scan3d_server::ingest::pki::{PairRequest, pair};

fn scan3d(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_scan3d"))
        .args(args)
        .env("RUST_LOG", "error")
        .output()
        .unwrap()
}

/// The error line: the last line of stderr, which must be the only line starting `scan3d:`.
fn error_line(out: &Output) -> String {
    let stderr = String::from_utf8_lossy(&out.stderr);
    let lines: Vec<&str> = stderr
        .lines()
        .filter(|l| l.starts_with("scan3d: "))
        .collect();
    assert_eq!(lines.len(), 1, "{stderr}");
    lines[0].to_owned()
}

/// A paired PKI and a server.toml listening on an ephemeral loopback port.
fn config(dir: &Path, data_dir: &Path) -> std::path::PathBuf {
    let pki = dir.join("pki");
    pair(&PairRequest {
        dir: pki.clone(),
        edge: "pi-01".into(),
        server_names: vec![],
        force: false,
    })
    .unwrap();
    let path = dir.join("server.toml");
    std::fs::write(
        &path,
        format!(
            "listen = \"127.0.0.1:0\"\npki_dir = {:?}\ndata_dir = {:?}\n",
            pki.display().to_string(),
            data_dir.display().to_string()
        ),
    )
    .unwrap();
    path
}

#[test]
fn a_control_socket_path_longer_than_sun_path_stops_serve_at_start() {
    let tmp = tempfile::tempdir().unwrap();
    let data_dir = tmp.path().join("d".repeat(110));
    let config = config(tmp.path(), &data_dir);
    let out = scan3d(&["serve", "--config", config.to_str().unwrap()]);
    assert!(!out.status.success());
    let line = error_line(&out);
    let socket = data_dir.join("control.sock");
    assert_eq!(
        line,
        format!(
            "scan3d: control socket path {} is {} bytes, longer than the 107 bytes a Unix socket path may have; choose a shorter data_dir",
            socket.display(),
            socket.as_os_str().len()
        )
    );
}

#[test]
fn an_unusable_data_dir_is_named_in_the_error() {
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join("not-a-dir");
    std::fs::write(&file, "").unwrap();
    let data_dir = file.join("data");
    let config = config(tmp.path(), &data_dir);
    let out = scan3d(&["serve", "--config", config.to_str().unwrap()]);
    assert!(!out.status.success());
    assert_eq!(
        error_line(&out),
        format!(
            "scan3d: data_dir {}: Not a directory (os error 20)",
            data_dir.display()
        )
    );
}

#[test]
fn a_cause_is_printed_once() {
    let out = scan3d(&["serve", "--config", "/nonexistent/scan3d/server.toml"]);
    assert!(!out.status.success());
    assert_eq!(
        error_line(&out),
        "scan3d: cannot read /nonexistent/scan3d/server.toml: No such file or directory (os error 2)"
    );
}
