//! The daemon at its default level, as an operator sees it with stderr redirected to a file:
//! a start line naming the config, one error per missing device naming its path and the hint,
//! and no ANSI colour codes.

use std::io::Read;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// Waits until `done(stderr so far)` holds, for a generous deadline, then returns the text.
fn wait_for(file: &std::path::Path, what: &str, done: impl Fn(&str) -> bool) -> String {
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let mut text = String::new();
        if let Ok(mut f) = std::fs::File::open(file) {
            let _ = f.read_to_string(&mut text);
        }
        if done(&text) {
            return text;
        }
        assert!(
            Instant::now() < deadline,
            "no {what} within 60 s; stderr:\n{text}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

#[test]
fn missing_devices_are_errors_naming_their_paths_without_colour_codes() {
    let dir = tempfile::tempdir().unwrap();
    let sweep = dir.path().join("ttySWEEP");
    let socket = dir.path().join("i2c.sock");
    let config = dir.path().join("edge.toml");
    std::fs::write(
        &config,
        format!(
            "device_name = \"t\"\nstate_dir = \"{}\"\n[sweep]\npath = \"{}\"\n\
             [i2c]\nsocket = \"{}\"\n[imu]\n",
            dir.path().join("state").display(),
            sweep.display(),
            socket.display()
        ),
    )
    .unwrap();
    let log = dir.path().join("stderr.log");
    let mut child = Command::new(env!("CARGO_BIN_EXE_scan3d-edge"))
        .arg("--config")
        .arg(&config)
        .env_remove("RUST_LOG")
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log).unwrap())
        .spawn()
        .unwrap();
    let sweep_error = format!(
        "cannot open {}: {} does not exist",
        sweep.display(),
        sweep.display()
    );
    let text = wait_for(&log, "error lines", |text| {
        text.contains(&sweep_error) && text.contains("IMU lost")
    });
    child.kill().unwrap();
    child.wait().unwrap();

    assert!(
        !text.contains('\x1b'),
        "ANSI codes in a redirected log:\n{text}"
    );
    let start = text
        .lines()
        .find(|l| l.contains("edge daemon starting"))
        .expect("a start line");
    assert!(start.contains(&config.display().to_string()), "{start}");
    let sweep_lines: Vec<&str> = text.lines().filter(|l| l.contains(&sweep_error)).collect();
    assert_eq!(sweep_lines.len(), 1, "repeated within a minute:\n{text}");
    assert!(
        sweep_lines[0].contains("ERROR") && sweep_lines[0].contains("plugged in"),
        "{text}"
    );
    let socket_line = text
        .lines()
        .find(|l| l.contains("cannot open the I2C socket"))
        .expect("the socket's error");
    assert!(
        socket_line.contains(&socket.display().to_string()),
        "{socket_line}"
    );
    assert_eq!(text.matches("IMU lost").count(), 1, "{text}");
}
