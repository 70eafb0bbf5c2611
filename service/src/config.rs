//! TOML configuration files: parse into any `serde` type, with errors that name the file and
//! the line of the offending key.

use std::path::{Path, PathBuf};

use serde::de::DeserializeOwned;

/// Why a configuration file could not be used.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The file could not be read.
    #[error("cannot read {path}: {error}")]
    Read {
        /// The file.
        path: PathBuf,
        /// The I/O error (in the message, so not also a `source()`: printed once).
        error: std::io::Error,
    },
    /// The TOML is malformed or has unknown, mistyped or out-of-range keys.
    #[error("{path}: {message}")]
    Parse {
        /// The file.
        path: PathBuf,
        /// The parser's message, starting with `line N:` when the place is known.
        message: String,
    },
}

/// Parses TOML text; `origin` names it in errors.
pub fn parse_toml<T: DeserializeOwned>(text: &str, origin: &Path) -> Result<T, ConfigError> {
    toml::from_str(text).map_err(|e| {
        let message = match e.span() {
            Some(span) => {
                let before = text.get(..span.start).unwrap_or_default();
                let line = before.bytes().filter(|&b| b == b'\n').count() + 1;
                format!("line {line}: {}", e.message())
            }
            None => e.message().to_string(),
        };
        ConfigError::Parse {
            path: origin.to_path_buf(),
            message,
        }
    })
}

/// Reads and parses the TOML file at `path`.
pub fn load_toml<T: DeserializeOwned>(path: &Path) -> Result<T, ConfigError> {
    parse_toml(&read_text(path)?, path)
}

/// Reads a configuration file's text; a failure is [`ConfigError::Read`] naming the path.
pub fn read_text(path: &Path) -> Result<String, ConfigError> {
    std::fs::read_to_string(path).map_err(|error| ConfigError::Read {
        path: path.to_path_buf(),
        error,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, serde::Deserialize)]
    #[serde(deny_unknown_fields)]
    #[allow(dead_code)]
    struct Example {
        name: String,
        #[serde(default)]
        count: u32,
    }

    #[test]
    fn errors_name_the_file_and_the_line() {
        let err =
            parse_toml::<Example>("name = \"a\"\n\ncont = 3\n", Path::new("x.toml")).unwrap_err();
        let text = err.to_string();
        assert!(
            text.starts_with("x.toml: line 3: unknown field `cont`"),
            "{text}"
        );
    }

    #[test]
    fn a_missing_file_is_a_read_error_naming_it_and_its_cause_once() {
        let err = load_toml::<Example>(Path::new("/nonexistent/scan3d.toml")).unwrap_err();
        assert!(matches!(err, ConfigError::Read { .. }));
        assert!(err.to_string().contains("/nonexistent/scan3d.toml"));
        // However it is printed: the cause is in the message and not chained again.
        assert!(std::error::Error::source(&err).is_none());
        let printed = format!("{:#}", anyhow_like(&err));
        assert_eq!(
            printed.matches("No such file or directory").count(),
            1,
            "{printed}"
        );
    }

    /// `{:#}` as anyhow prints it: every level of the chain joined by ": ".
    fn anyhow_like(e: &(dyn std::error::Error + 'static)) -> String {
        let mut out = e.to_string();
        let mut cause = e.source();
        while let Some(c) = cause {
            out.push_str(&format!(": {c}"));
            cause = c.source();
        }
        out
    }
}
