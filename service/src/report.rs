//! One readable line for an error and its causes, as the CLIs print it before exiting non-zero.

use std::error::Error;

/// `error: cause: cause…`, each cause once.
///
/// Many error types already put their cause in their own message *and* return it from
/// [`Error::source`] (a `thiserror` variant with a `source` field and `{source}` in its text),
/// so printing every level, as anyhow's `{:#}` does, shows such a cause twice. A cause whose
/// text the line already contains is skipped; one that adds something is appended.
pub fn error_chain(error: &(dyn Error + 'static)) -> String {
    let mut line = error.to_string();
    let mut cause = error.source();
    while let Some(e) = cause {
        let text = e.to_string();
        if !text.is_empty() && !line.contains(&text) {
            line.push_str(": ");
            line.push_str(&text);
        }
        cause = e.source();
    }
    line
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, thiserror::Error)]
    #[error("cannot read {path}: {source}")]
    struct Repeats {
        path: &'static str,
        source: std::io::Error,
    }

    #[derive(Debug, thiserror::Error)]
    #[error("loading the configuration")]
    struct Wraps(#[source] Repeats);

    #[test]
    fn a_cause_already_in_the_message_is_printed_once() {
        let e = Repeats {
            path: "/etc/x.toml",
            source: std::io::Error::new(std::io::ErrorKind::NotFound, "no such file"),
        };
        assert_eq!(error_chain(&e), "cannot read /etc/x.toml: no such file");
    }

    #[test]
    fn causes_that_add_something_are_appended_in_order() {
        let e = Wraps(Repeats {
            path: "/etc/x.toml",
            source: std::io::Error::new(std::io::ErrorKind::NotFound, "no such file"),
        });
        assert_eq!(
            error_chain(&e),
            "loading the configuration: cannot read /etc/x.toml: no such file"
        );
    }
}
