//! `scan3d scan`, the real binary, against a running control socket: a scan to an edge that is
//! not connected is one readable line and a non-zero exit (and, with `--json`, the status as
//! JSON); without a server, the same.

use std::path::Path;
use std::process::Command;

use scan3d_server::ingest::control::{ControlLimits, ControlSocket, EdgeControl, socket_path};

fn scan3d(data_dir: &Path, args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_scan3d"))
        .arg("scan")
        .args(args)
        .arg("--data-dir")
        .arg(data_dir)
        .output()
        .expect("scan3d runs");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn a_scan_to_an_edge_that_is_not_connected_fails_with_one_line() {
    let dir = tempfile::tempdir().expect("tempdir");
    // No server at all.
    let (ok, stdout, stderr) = scan3d(dir.path(), &["--edge", "pi", "--at", "1,2", "--wait"]);
    assert!(!ok);
    assert_eq!(stdout, "");
    assert_eq!(stderr.lines().count(), 1, "{stderr}");
    assert!(
        stderr.starts_with("scan3d: cannot reach the server's control socket"),
        "{stderr}"
    );

    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .expect("runtime");
    let socket = runtime.block_on(async {
        ControlSocket::bind(socket_path(dir.path()), ControlLimits::default())
            .await
            .expect("socket")
    });
    runtime.spawn(socket.serve(EdgeControl::default()));

    let (ok, stdout, stderr) = scan3d(
        dir.path(),
        &["--edge", "pi", "--at", "1,2,90", "--name", "door", "--wait"],
    );
    assert!(!ok);
    assert_eq!(stdout, "");
    assert_eq!(
        stderr.trim_end(),
        "scan3d: edge \"pi\" is not connected (connected: none)"
    );
    let (ok, stdout, _) = scan3d(dir.path(), &["--edge", "pi", "--stop", "--json"]);
    assert!(!ok);
    let status: serde_json::Value = serde_json::from_str(&stdout).expect("JSON status");
    assert_eq!(status["state"], "not_connected");
    assert_eq!(status["ok"], false);
    assert_eq!(status["done"], true);
}
