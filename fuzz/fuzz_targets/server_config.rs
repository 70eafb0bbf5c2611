//! `server.toml`: any text parses or fails with an error, within the reader budget; a config
//! that parses yields the intervals and paths `serve` derives from it.
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;
use scan3d_server::config::ServerConfig;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    scan3d_fuzz::with_reader_budget(data.len(), || {
        let Ok(config) = ServerConfig::from_toml_str(text, Path::new("server.toml")) else {
            return;
        };
        assert!(!config.commit_interval().is_zero());
        assert!(!config.time_sync_interval().is_zero());
        assert!(config.max_connections > 0);
        let _ = config.sessions_dir();
        let _ = scan3d_server::ingest::control::socket_path(&config.data_dir);
    });
});
