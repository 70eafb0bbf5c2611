//! `scan3d pair`: create the CA (first time), the server certificate and an edge bundle.

use std::io::Write;
use std::path::PathBuf;

use crate::ingest::pki::{self, PairRequest, Provenance};

/// Options of `scan3d pair`.
#[derive(Debug, clap::Args)]
pub struct PairArgs {
    /// PKI directory (created if missing; see `DIR/ca.pem`, `DIR/server/`, `DIR/edges/`).
    #[arg(long, value_name = "DIR")]
    pub dir: PathBuf,
    /// Name of the edge to pair: its certificate CN and its name on the server.
    #[arg(long, value_name = "NAME")]
    pub edge: String,
    /// Host name or IP the edges use to reach the server (repeatable). Given: the server
    /// certificate is re-issued for exactly these names. Omitted: the existing server
    /// certificate is kept, or one for `localhost` and `127.0.0.1` is created.
    #[arg(long = "server-name", value_name = "HOST")]
    pub server_names: Vec<String>,
    /// Issue a new bundle even if this edge already has one.
    #[arg(long)]
    pub force: bool,
}

/// Runs `scan3d pair`: pairs the edge and prints what was created and the next step.
pub fn run(args: &PairArgs, out: &mut dyn Write) -> anyhow::Result<()> {
    let outcome = pki::pair(&PairRequest {
        dir: args.dir.clone(),
        edge: args.edge.clone(),
        server_names: args.server_names.clone(),
        force: args.force,
    })?;
    let verb = |p: Provenance| match p {
        Provenance::Created => "created",
        Provenance::Replaced => "replaced",
        Provenance::Reused => "kept",
    };
    writeln!(
        out,
        "CA {}: {} ({})",
        verb(outcome.ca),
        outcome.ca_cert.display(),
        outcome.ca_key.display()
    )?;
    writeln!(
        out,
        "server certificate {}: {} for {}",
        verb(outcome.server),
        outcome.server_cert.display(),
        outcome.server_names.join(", ")
    )?;
    writeln!(
        out,
        "edge bundle {} for {:?}: {}",
        verb(outcome.edge),
        args.edge,
        outcome.edge_dir.display()
    )?;
    if outcome.server == Provenance::Replaced {
        writeln!(
            out,
            "restart `scan3d serve` to use the new server certificate"
        )?;
    }
    writeln!(
        out,
        "next: copy the bundle to the Pi and point edge.toml at it, e.g.\n  scp -r {} pi:/etc/scan3d/pki",
        outcome.edge_dir.display()
    )?;
    writeln!(
        out,
        "the edge must connect with one of the server names above: {}",
        outcome.server_names.join(", ")
    )?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use clap::Parser;

    use crate::cli::{Cli, execute};

    fn run(args: &[&str]) -> anyhow::Result<String> {
        let cli = Cli::try_parse_from(args)?;
        let mut out = Vec::new();
        execute(cli, &mut out)?;
        Ok(String::from_utf8(out)?)
    }

    #[test]
    fn pair_prints_what_it_made_and_the_next_step() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().display().to_string();
        let first = run(&[
            "scan3d",
            "pair",
            "--dir",
            &dir,
            "--edge",
            "pi-01",
            "--server-name",
            "scanhost",
            "--server-name",
            "10.1.2.3",
        ])
        .unwrap();
        assert!(first.contains("CA created"), "{first}");
        assert!(first.contains("server certificate created"), "{first}");
        assert!(first.contains("for scanhost, 10.1.2.3"), "{first}");
        assert!(
            first.contains(&format!("scp -r {dir}/edges/pi-01 pi:/etc/scan3d/pki")),
            "{first}"
        );
        assert!(tmp.path().join("edges/pi-01/edge.key").is_file());

        let second = run(&["scan3d", "pair", "--dir", &dir, "--edge", "pi-02"]).unwrap();
        assert!(second.contains("CA kept"), "{second}");
        assert!(second.contains("server certificate kept"), "{second}");
        assert!(second.contains("for scanhost, 10.1.2.3"), "{second}");

        let again = run(&["scan3d", "pair", "--dir", &dir, "--edge", "pi-02"]).unwrap_err();
        assert!(again.to_string().contains("--force"), "{again}");
        let forced = run(&[
            "scan3d", "pair", "--dir", &dir, "--edge", "pi-02", "--force",
        ])
        .unwrap();
        assert!(forced.contains("edge bundle replaced"), "{forced}");
    }

    #[test]
    fn dir_and_edge_are_required() {
        assert!(Cli::try_parse_from(["scan3d", "pair", "--edge", "pi-01"]).is_err());
        assert!(Cli::try_parse_from(["scan3d", "pair", "--dir", "/tmp/x"]).is_err());
    }
}
