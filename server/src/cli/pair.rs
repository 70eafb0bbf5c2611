//! `scan3d pair`: create the CA (first time), the server certificate and an edge bundle;
//! renew or revoke an edge's certificate.
//!
//! Keep `ca.key` off the server host: pair on the operator's machine (or bring the key back
//! from offline storage only to pair, renew or revoke) and copy `ca.pem`, `crl.pem` and
//! `server/` to the server. The server never reads `ca.key`.

use std::io::Write;
use std::path::PathBuf;
use std::time::SystemTime;

use crate::ingest::pki::{self, PairOutcome, PairRequest, Provenance, Validity};

/// Options of `scan3d pair`.
#[derive(Debug, clap::Args)]
#[command(
    group(clap::ArgGroup::new("action").required(true).args(["edge", "renew", "revoke"])),
    after_help = "Keep DIR/ca.key off the server host: the server needs only ca.pem, crl.pem and \
                  server/. Revocations and renewals take effect when the server reloads: \
                  `systemctl reload scan3d-server` (SIGHUP) or a restart."
)]
pub struct PairArgs {
    /// PKI directory (created if missing; see `DIR/ca.pem`, `DIR/server/`, `DIR/edges/`).
    #[arg(long, value_name = "DIR")]
    pub dir: PathBuf,
    /// Name of the edge to pair: its certificate CN and its name on the server.
    #[arg(long, value_name = "NAME")]
    pub edge: Option<String>,
    /// Issue a fresh bundle (new key, new serial, new validity) for an edge paired before,
    /// and revoke its earlier certificates. With `--server-name`, renew the server
    /// certificate too.
    #[arg(long, value_name = "NAME", conflicts_with = "force")]
    pub renew: Option<String>,
    /// Revoke every certificate issued to this edge (written to `DIR/crl.pem`).
    #[arg(long, value_name = "NAME", conflicts_with_all = ["force", "server_names", "validity_days", "ca_validity_days"])]
    pub revoke: Option<String>,
    /// Host name or IP the edges use to reach the server (repeatable). Given: the server
    /// certificate is re-issued for exactly these names. Omitted: the existing server
    /// certificate is kept, or one for `localhost` and `127.0.0.1` is created.
    #[arg(long = "server-name", value_name = "HOST")]
    pub server_names: Vec<String>,
    /// Issue a new bundle even if this edge already has one; its earlier certificates are
    /// revoked.
    #[arg(long)]
    pub force: bool,
    /// Validity of the edge and server certificates issued by this run, in days.
    #[arg(long, value_name = "DAYS", default_value_t = Validity::default().leaf_days)]
    pub validity_days: u32,
    /// Validity of the CA, in days, when this run creates it.
    #[arg(long, value_name = "DAYS", default_value_t = Validity::default().ca_days)]
    pub ca_validity_days: u32,
}

/// Runs `scan3d pair`: pairs, renews or revokes, and prints what was done and the next step.
pub fn run(args: &PairArgs, out: &mut dyn Write) -> anyhow::Result<()> {
    let now = SystemTime::now();
    let validity = Validity {
        leaf_days: args.validity_days,
        ca_days: args.ca_validity_days,
    };
    if let Some(name) = &args.revoke {
        let outcome = pki::revoke(&args.dir, name, now)?;
        if outcome.revoked.is_empty() {
            writeln!(out, "every certificate of {name:?} was already revoked")?;
        } else {
            writeln!(
                out,
                "revoked {name:?}: serial {}",
                outcome.revoked.join(", serial ")
            )?;
        }
        writeln!(
            out,
            "revocation list: {}\nnext: copy it to the server's pki_dir if the server has its own copy, then reload the server (`systemctl reload scan3d-server`, or SIGHUP)",
            outcome.crl.display()
        )?;
        return Ok(());
    }
    let (outcome, name) = match (&args.renew, &args.edge) {
        (Some(name), _) => (
            pki::renew(&args.dir, name, &args.server_names, validity, now)?,
            name,
        ),
        (None, Some(name)) => {
            let request = PairRequest {
                dir: args.dir.clone(),
                edge: name.clone(),
                server_names: args.server_names.clone(),
                force: args.force,
            };
            (pki::pair_with(&request, validity, now)?, name)
        }
        (None, None) => anyhow::bail!("one of --edge, --renew or --revoke is required"),
    };
    print_outcome(&outcome, name, out)
}

fn print_outcome(outcome: &PairOutcome, name: &str, out: &mut dyn Write) -> anyhow::Result<()> {
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
        name,
        outcome.edge_dir.display()
    )?;
    if !outcome.revoked.is_empty() {
        writeln!(
            out,
            "revoked the earlier certificate(s) of {name:?}: serial {}; they stop working when the server reloads (`systemctl reload scan3d-server`, or SIGHUP)",
            outcome.revoked.join(", serial ")
        )?;
    }
    if outcome.server == Provenance::Replaced {
        writeln!(
            out,
            "restart `scan3d serve` to use the new server certificate"
        )?;
    }
    writeln!(out, "{}", copy_hint(&outcome.edge_dir))?;
    writeln!(
        out,
        "the edge must connect with one of the server names above: {}",
        outcome.server_names.join(", ")
    )?;
    writeln!(
        out,
        "keep {} off the server host; the server needs only ca.pem, crl.pem and server/",
        outcome.ca_key.display()
    )?;
    Ok(())
}

/// The next step after pairing: the bundle's files (not its directory) into the Pi's
/// `/etc/scan3d/pki`, owned by `scan3d` and keeping `edge.key`'s 0600, as deploy/README.md §2
/// does it (`scp -r DIR pi:/etc/scan3d/pki` would nest them one directory too deep).
fn copy_hint(edge_dir: &std::path::Path) -> String {
    format!(
        "next: copy the bundle's files into the Pi's /etc/scan3d/pki (as in deploy/README.md), e.g.\n  \
         sudo tar -C {} -c . | ssh pi@raspberrypi.local \\\n    \
         'sudo install -d -m 0755 /etc/scan3d && sudo install -d -m 0700 -o scan3d -g scan3d /etc/scan3d/pki &&\n     \
         sudo tar -C /etc/scan3d/pki --no-same-owner -x && sudo chown -R scan3d:scan3d /etc/scan3d/pki'",
        edge_dir.display()
    )
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
        // The copy hint is deploy/README.md's tar pipe, with this bundle's directory.
        let hint: Vec<&str> = first
            .lines()
            .skip_while(|l| !l.starts_with("next: "))
            .take(4)
            .collect();
        assert_eq!(
            hint,
            [
                "next: copy the bundle's files into the Pi's /etc/scan3d/pki (as in deploy/README.md), e.g.",
                &format!("  sudo tar -C {dir}/edges/pi-01 -c . | ssh pi@raspberrypi.local \\"),
                "    'sudo install -d -m 0755 /etc/scan3d && sudo install -d -m 0700 -o scan3d -g scan3d /etc/scan3d/pki &&",
                "     sudo tar -C /etc/scan3d/pki --no-same-owner -x && sudo chown -R scan3d:scan3d /etc/scan3d/pki'",
            ]
        );
        let readme = include_str!("../../../deploy/README.md");
        for line in &hint[2..] {
            assert!(
                readme.contains(line.trim()),
                "not in deploy/README.md: {line}"
            );
        }
        assert!(
            readme.contains(
                "sudo tar -C /etc/scan3d/pki/edges/edge-pi-01 -c . | ssh pi@raspberrypi.local \\"
            ),
            "deploy/README.md's tar pipe changed"
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
        assert!(
            forced.contains("revoked the earlier certificate"),
            "{forced}"
        );

        let renewed = run(&["scan3d", "pair", "--dir", &dir, "--renew", "pi-02"]).unwrap();
        assert!(renewed.contains("edge bundle replaced"), "{renewed}");
        assert!(
            renewed.contains("revoked the earlier certificate"),
            "{renewed}"
        );
        let with_server = run(&[
            "scan3d",
            "pair",
            "--dir",
            &dir,
            "--renew",
            "pi-02",
            "--server-name",
            "newhost",
        ])
        .unwrap();
        assert!(
            with_server.contains("server certificate replaced")
                && with_server.contains("for newhost"),
            "{with_server}"
        );
        let revoked = run(&["scan3d", "pair", "--dir", &dir, "--revoke", "pi-02"]).unwrap();
        assert!(
            revoked.starts_with("revoked \"pi-02\": serial "),
            "{revoked}"
        );
        let again = run(&["scan3d", "pair", "--dir", &dir, "--revoke", "pi-02"]).unwrap();
        assert!(
            again.starts_with("every certificate of \"pi-02\" was already revoked"),
            "{again}"
        );
        let unknown = run(&["scan3d", "pair", "--dir", &dir, "--revoke", "nobody"]).unwrap_err();
        assert!(
            unknown.to_string().contains("no certificate was issued"),
            "{unknown}"
        );
    }

    #[test]
    fn dir_and_exactly_one_action_are_required() {
        assert!(Cli::try_parse_from(["scan3d", "pair", "--edge", "pi-01"]).is_err());
        assert!(Cli::try_parse_from(["scan3d", "pair", "--dir", "/tmp/x"]).is_err());
        let both = [
            "scan3d", "pair", "--dir", "/x", "--edge", "a", "--revoke", "a",
        ];
        assert!(Cli::try_parse_from(both).is_err());
        let forced_revoke = ["scan3d", "pair", "--dir", "/x", "--revoke", "a", "--force"];
        assert!(Cli::try_parse_from(forced_revoke).is_err());
        assert!(Cli::try_parse_from(["scan3d", "pair", "--dir", "/x", "--renew", "a"]).is_ok());
    }
}
