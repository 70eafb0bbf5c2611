//! The private PKI behind the uplink's mutual TLS: one CA, one server certificate, one bundle
//! per edge (`scan3d pair`).
//!
//! Layout of the PKI directory `DIR` (directories are created `0700`, keys `0600`):
//!
//! ```text
//! DIR/ca.pem                  CA certificate (created on first use, never overwritten)
//! DIR/ca.key                  CA private key (PKCS#8 PEM); keep it off the server host
//! DIR/crl.pem                 revocation list signed by the CA (X.509 CRL, PEM)
//! DIR/issued.tsv              every certificate issued: serial, kind, name, expiry, revocation
//! DIR/server/server.pem       server certificate; SANs = the server's host names / IPs
//! DIR/server/server.key       server private key
//! DIR/edges/NAME/edge.pem     edge certificate, CN = NAME (also a DNS SAN), EKU clientAuth
//! DIR/edges/NAME/edge.key     edge private key
//! DIR/edges/NAME/ca.pem       copy of DIR/ca.pem, so the bundle is self-contained
//! ```
//!
//! `DIR/edges/NAME` is the bundle to copy to the Pi. The server loads `DIR/ca.pem`,
//! `DIR/crl.pem` and `DIR/server/*` (see [`super::tls::server_config`]) and trusts any client
//! certificate the CA signed and did not revoke; the certificate's CN becomes the edge's
//! identity. The server never needs `ca.key`: pair on the operator's machine (or keep `ca.key`
//! offline and bring it back only to pair, renew or revoke), then copy `ca.pem`, `crl.pem`
//! and `server/` to the server host.
//!
//! Keys are ECDSA P-256. Validity: certificates start on 1975-01-01 (the Pi has no real-time
//! clock and may run with a date far in the past until NTP answers) and end
//! [`Validity::leaf_days`] (default 2 years) after issue for edge and server certificates,
//! [`Validity::ca_days`] (default 10 years) for the CA. The server, which has a clock, refuses
//! expired edge certificates; the edge cannot reliably refuse an expired server certificate
//! before its clock is set.
//!
//! Revocation is by serial number: [`revoke`] marks every unrevoked certificate issued to an
//! edge name in `issued.tsv` and re-signs `crl.pem`. Re-issuing an edge's bundle ([`pair`] with
//! `force`, or [`renew`]) revokes the certificates it had before, so a copied-away old key
//! stops working. The server reads the list at start and on SIGHUP. Files are written to a
//! temporary name and then moved into place, so a crash never leaves a half-written key.

use std::fs::{self, DirBuilder, File, OpenOptions};
use std::io::{self, Write};
use std::net::IpAddr;
use std::os::unix::fs::{DirBuilderExt, OpenOptionsExt};
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime};

use rcgen::{
    BasicConstraints, CertificateParams, CertificateRevocationListParams, DistinguishedName,
    DnType, ExtendedKeyUsagePurpose, IsCa, Issuer, KeyIdMethod, KeyPair, KeyUsagePurpose,
    RevocationReason, RevokedCertParams, SerialNumber,
};
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, CertificateRevocationListDer, ServerName};
use scan3d_service::link::{PemError, check_key_mode};
use time::OffsetDateTime;

/// Host names / IPs of the server certificate when none are given.
pub const DEFAULT_SERVER_NAMES: [&str; 2] = ["localhost", "127.0.0.1"];
/// Longest accepted edge name (one DNS label).
pub const MAX_EDGE_NAME_LEN: usize = 63;

const KEY_MODE: u32 = 0o600;
const CERT_MODE: u32 = 0o644;
const DIR_MODE: u32 = 0o700;

/// File names inside the PKI directory (see the module docs).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Layout {
    root: PathBuf,
}

impl Layout {
    /// The layout rooted at `dir`.
    pub fn new(dir: impl Into<PathBuf>) -> Self {
        Layout { root: dir.into() }
    }
    /// `DIR/ca.pem`.
    pub fn ca_cert(&self) -> PathBuf {
        self.root.join("ca.pem")
    }
    /// `DIR/ca.key`.
    pub fn ca_key(&self) -> PathBuf {
        self.root.join("ca.key")
    }
    /// `DIR`.
    pub fn root(&self) -> &Path {
        &self.root
    }
    /// `DIR/crl.pem`: the revocation list the server reads.
    pub fn crl(&self) -> PathBuf {
        self.root.join("crl.pem")
    }
    /// `DIR/issued.tsv`: the ledger of issued certificates.
    pub fn issued(&self) -> PathBuf {
        self.root.join("issued.tsv")
    }
    /// `DIR/server`.
    pub fn server_dir(&self) -> PathBuf {
        self.root.join("server")
    }
    /// `DIR/server/server.pem`.
    pub fn server_cert(&self) -> PathBuf {
        self.server_dir().join("server.pem")
    }
    /// `DIR/server/server.key`.
    pub fn server_key(&self) -> PathBuf {
        self.server_dir().join("server.key")
    }
    /// `DIR/edges/NAME`: the bundle to copy to the Pi.
    pub fn edge_dir(&self, name: &str) -> PathBuf {
        self.root.join("edges").join(name)
    }
    /// `DIR/edges/NAME/edge.pem`.
    pub fn edge_cert(&self, name: &str) -> PathBuf {
        self.edge_dir(name).join("edge.pem")
    }
    /// `DIR/edges/NAME/edge.key`.
    pub fn edge_key(&self, name: &str) -> PathBuf {
        self.edge_dir(name).join("edge.key")
    }
    /// `DIR/edges/NAME/ca.pem`.
    pub fn edge_ca_cert(&self, name: &str) -> PathBuf {
        self.edge_dir(name).join("ca.pem")
    }
}

/// What `scan3d pair` should do.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PairRequest {
    /// The PKI directory (created if missing).
    pub dir: PathBuf,
    /// The edge's name: its certificate CN and its identity on the server.
    pub edge: String,
    /// Server host names / IPs for the server certificate. Empty: keep the existing server
    /// certificate, or create one for [`DEFAULT_SERVER_NAMES`] if there is none.
    pub server_names: Vec<String>,
    /// Replace an existing bundle for this edge instead of refusing.
    pub force: bool,
}

/// How long new certificates are valid.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Validity {
    /// Edge and server certificates, days from issue.
    pub leaf_days: u32,
    /// The CA certificate (when this run creates it), days from creation.
    pub ca_days: u32,
}

impl Validity {
    /// Longest accepted validity, days (100 years).
    pub const MAX_DAYS: u32 = 36_525;
}

impl Default for Validity {
    /// Two years for edge and server certificates, ten for the CA.
    fn default() -> Self {
        Validity {
            leaf_days: 730,
            ca_days: 3650,
        }
    }
}

/// Whether a file set was made by this run or already there.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Provenance {
    /// Created by this run; nothing was there before.
    Created,
    /// Created by this run, replacing what was there.
    Replaced,
    /// Already there and kept as is.
    Reused,
}

/// What [`pair`] did, with the paths it touched.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PairOutcome {
    /// The CA (`ca.pem`, `ca.key`): created on first use, reused afterwards.
    pub ca: Provenance,
    /// `DIR/ca.pem`.
    pub ca_cert: PathBuf,
    /// `DIR/ca.key`.
    pub ca_key: PathBuf,
    /// The server certificate and key.
    pub server: Provenance,
    /// `DIR/server/server.pem`.
    pub server_cert: PathBuf,
    /// `DIR/server/server.key`.
    pub server_key: PathBuf,
    /// The server certificate's SANs (as found in it when reused).
    pub server_names: Vec<String>,
    /// The edge bundle (`Created`, or `Replaced` with `force`).
    pub edge: Provenance,
    /// `DIR/edges/NAME`: the directory to copy to the Pi.
    pub edge_dir: PathBuf,
    /// Serial numbers (hex) of the edge's earlier certificates this run revoked.
    pub revoked: Vec<String>,
}

/// What [`revoke`] did.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RevokeOutcome {
    /// Serial numbers (hex) newly revoked.
    pub revoked: Vec<String>,
    /// `DIR/crl.pem`.
    pub crl: PathBuf,
}

/// Why pairing failed. Every variant that concerns a file names it.
#[derive(Debug, thiserror::Error)]
pub enum PkiError {
    /// The edge name is not usable as a certificate name and a directory name.
    #[error("invalid edge name {name:?}: {reason}")]
    InvalidEdgeName {
        /// The rejected name.
        name: String,
        /// What is wrong with it.
        reason: &'static str,
    },
    /// A server name is neither an IP address nor a valid DNS name.
    #[error("invalid server name {name:?}: not an IP address or a DNS name")]
    InvalidServerName {
        /// The rejected name.
        name: String,
    },
    /// The edge already has a bundle and `force` was not given.
    #[error(
        "edge bundle {} already exists; pass --force (or use --renew) to issue a new one and revoke the old certificate",
        dir.display()
    )]
    BundleExists {
        /// The existing bundle directory.
        dir: PathBuf,
    },
    /// Only one of `ca.pem` / `ca.key` exists.
    #[error(
        "incomplete CA: {} exists but {} is missing; restore it, or move {} away to start a new CA (every edge must then be paired again)",
        present.display(), missing.display(), present.display()
    )]
    IncompleteCa {
        /// The file that exists.
        present: PathBuf,
        /// The file that is missing.
        missing: PathBuf,
    },
    /// Reading or writing a file failed.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// The OS error.
        source: io::Error,
    },
    /// A PEM file holds no usable certificate or key.
    #[error("{}: {reason}", path.display())]
    BadFile {
        /// The file.
        path: PathBuf,
        /// What is wrong with it.
        reason: String,
    },
    /// `ca.key` is not the key of `ca.pem`.
    #[error("{} is not the private key of {}", key.display(), cert.display())]
    CaKeyMismatch {
        /// `ca.pem`.
        cert: PathBuf,
        /// `ca.key`.
        key: PathBuf,
    },
    /// Nothing was ever issued to this edge name.
    #[error("no certificate was issued to edge {name:?} in {}", dir.display())]
    UnknownEdge {
        /// The edge name.
        name: String,
        /// The PKI directory.
        dir: PathBuf,
    },
    /// A validity of 0 days or more than [`Validity::MAX_DAYS`].
    #[error("validity of {days} days: must be 1 to {} days", Validity::MAX_DAYS)]
    BadValidity {
        /// The requested number of days.
        days: u32,
    },
    /// A private key file is unusable (e.g. readable by other users).
    #[error("{0}")]
    Key(PemError),
    /// rcgen could not generate a key or certificate.
    #[error("generating the {what}: {source}")]
    Generate {
        /// Which certificate or key.
        what: &'static str,
        /// rcgen's error.
        source: rcgen::Error,
    },
}

/// Checks that `name` can be an edge name: 1–63 characters of `[A-Za-z0-9._-]`, not starting
/// with `.`. It ends up as a certificate CN, a DNS SAN and a directory name on both sides.
pub fn validate_edge_name(name: &str) -> Result<(), PkiError> {
    let reason = if name.is_empty() {
        Some("it is empty")
    } else if name.len() > MAX_EDGE_NAME_LEN {
        Some("it is longer than 63 characters")
    } else if name.starts_with('.') {
        Some("it starts with '.'")
    } else if !name
        .bytes()
        .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'.' | b'_' | b'-'))
    {
        Some("only letters, digits, '.', '_' and '-' are allowed")
    } else {
        None
    };
    match reason {
        Some(reason) => Err(PkiError::InvalidEdgeName {
            name: name.to_owned(),
            reason,
        }),
        None => Ok(()),
    }
}

/// Creates or reuses the CA, (re)creates the server certificate when asked to, and issues the
/// edge bundle, with the default [`Validity`]. Nothing is written when the request is invalid
/// or the bundle exists without `force`. With `force`, the edge's earlier certificates are
/// revoked.
pub fn pair(req: &PairRequest) -> Result<PairOutcome, PkiError> {
    pair_with(req, Validity::default(), SystemTime::now())
}

/// [`pair`] with a chosen validity, as of `now` (tests issue certificates in the past).
pub fn pair_with(
    req: &PairRequest,
    validity: Validity,
    now: SystemTime,
) -> Result<PairOutcome, PkiError> {
    validate_edge_name(&req.edge)?;
    for days in [validity.leaf_days, validity.ca_days] {
        if days == 0 || days > Validity::MAX_DAYS {
            return Err(PkiError::BadValidity { days });
        }
    }
    let server_names = checked_server_names(&req.server_names)?;
    let layout = Layout::new(&req.dir);
    let edge_dir = layout.edge_dir(&req.edge);
    let bundle_files = [
        layout.edge_cert(&req.edge),
        layout.edge_key(&req.edge),
        layout.edge_ca_cert(&req.edge),
    ];
    let bundle_exists = bundle_files.iter().any(|p| p.exists());
    if bundle_exists && !req.force {
        return Err(PkiError::BundleExists { dir: edge_dir });
    }

    make_dir(&req.dir)?;
    let (ca, ca_status) = ensure_ca(&layout, validity, now)?;
    let mut ledger = Ledger::load(&layout)?;

    let existing_server = layout.server_cert().exists() && layout.server_key().exists();
    let (server_status, server_names) =
        if server_names.is_empty() && existing_server && ca_status == Provenance::Reused {
            (Provenance::Reused, read_san_names(&layout.server_cert())?)
        } else {
            let names = if server_names.is_empty() {
                DEFAULT_SERVER_NAMES.iter().map(|s| s.to_string()).collect()
            } else {
                server_names
            };
            let issued = write_server_cert(&layout, &ca, &names, validity, now)?;
            ledger.entries.push(issued);
            let status = if existing_server {
                Provenance::Replaced
            } else {
                Provenance::Created
            };
            (status, names)
        };

    // The certificate being replaced, if the ledger does not know it (a PKI from before the
    // ledger existed), is revoked too.
    ledger.adopt_bundle(&layout, &req.edge)?;
    let issued = write_edge_bundle(&layout, &ca, &req.edge, validity, now)?;
    let revoked = ledger.revoke_edge(&req.edge, now);
    ledger.entries.push(issued);
    ledger.save(&layout)?;
    write_crl(&layout, &ca, &ledger, now)?;
    Ok(PairOutcome {
        ca: ca_status,
        ca_cert: layout.ca_cert(),
        ca_key: layout.ca_key(),
        server: server_status,
        server_cert: layout.server_cert(),
        server_key: layout.server_key(),
        server_names,
        edge: if bundle_exists {
            Provenance::Replaced
        } else {
            Provenance::Created
        },
        edge_dir,
        revoked,
    })
}

/// Issues a fresh bundle (new key, new serial, validity from `now`) for an edge that was paired
/// before, and revokes its earlier certificates. The server keeps accepting the old certificate
/// until it reloads the list (SIGHUP), which leaves time to install the new bundle. Non-empty
/// `server_names` also renew the server certificate, for exactly those names.
pub fn renew(
    dir: &Path,
    edge: &str,
    server_names: &[String],
    validity: Validity,
    now: SystemTime,
) -> Result<PairOutcome, PkiError> {
    validate_edge_name(edge)?;
    let layout = Layout::new(dir);
    let known = layout.edge_cert(edge).exists()
        || Ledger::load(&layout)?
            .entries
            .iter()
            .any(|e| e.kind == IssuedKind::Edge && e.name == edge);
    if !known {
        return Err(PkiError::UnknownEdge {
            name: edge.to_owned(),
            dir: dir.to_path_buf(),
        });
    }
    let req = PairRequest {
        dir: dir.to_path_buf(),
        edge: edge.to_owned(),
        server_names: server_names.to_vec(),
        force: true,
    };
    pair_with(&req, validity, now)
}

/// Revokes every certificate issued to edge `name` that is not revoked yet and re-signs
/// `DIR/crl.pem`; the server refuses them from its next reload (SIGHUP) or start. The bundle
/// files stay where they are (they are useless now).
pub fn revoke(dir: &Path, name: &str, now: SystemTime) -> Result<RevokeOutcome, PkiError> {
    validate_edge_name(name)?;
    let layout = Layout::new(dir);
    let ca = load_ca(&layout.ca_cert(), &layout.ca_key())?;
    let mut ledger = Ledger::load(&layout)?;
    ledger.adopt_bundle(&layout, name)?;
    if !ledger
        .entries
        .iter()
        .any(|e| e.kind == IssuedKind::Edge && e.name == name)
    {
        return Err(PkiError::UnknownEdge {
            name: name.to_owned(),
            dir: dir.to_path_buf(),
        });
    }
    let revoked = ledger.revoke_edge(name, now);
    ledger.save(&layout)?;
    write_crl(&layout, &ca, &ledger, now)?;
    Ok(RevokeOutcome {
        revoked,
        crl: layout.crl(),
    })
}

/// Checks that `crl` (DER) is a CRL issued by the CA certificate at `ca_path` and returns how
/// many certificates it revokes. (webpki checks its signature at each handshake.)
pub fn check_crl(crl: &CertificateRevocationListDer<'_>, ca_path: &Path) -> Result<usize, String> {
    let (_, list) = x509_parser::parse_x509_crl(crl).map_err(|e| format!("not a CRL: {e}"))?;
    let ca_der = CertificateDer::from_pem_file(ca_path)
        .map_err(|e| format!("{}: {e}", ca_path.display()))?;
    let (_, ca) = x509_parser::parse_x509_certificate(&ca_der)
        .map_err(|e| format!("{}: {e}", ca_path.display()))?;
    if list.issuer().as_raw() != ca.subject().as_raw() {
        return Err(format!(
            "issued by {}, not by the CA {} ({})",
            list.issuer(),
            ca.subject(),
            ca_path.display()
        ));
    }
    Ok(list.iter_revoked_certificates().count())
}

/// What a ledger line is about.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum IssuedKind {
    Edge,
    Server,
}

/// One issued certificate in `issued.tsv`.
#[derive(Debug, Clone, PartialEq, Eq)]
struct Issued {
    /// Serial number, lower-case hex.
    serial: String,
    kind: IssuedKind,
    /// The edge name, or `server`.
    name: String,
    /// Expiry, Unix seconds.
    not_after: i64,
    /// Revocation time, Unix seconds.
    revoked: Option<i64>,
}

/// `DIR/issued.tsv`: one line per certificate issued, tab-separated:
/// `serial  kind  name  not_after_unix  revoked_unix|-`.
#[derive(Debug, Default)]
struct Ledger {
    entries: Vec<Issued>,
}

impl Ledger {
    const HEADER: &'static str = "# serial\tkind\tname\tnot_after_unix\trevoked_unix\n";

    fn load(layout: &Layout) -> Result<Self, PkiError> {
        let path = layout.issued();
        let text = match fs::read_to_string(&path) {
            Ok(text) => text,
            Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(Ledger::default()),
            Err(source) => return Err(PkiError::Io { path, source }),
        };
        let mut entries = Vec::new();
        for (number, line) in text.lines().enumerate() {
            if line.starts_with('#') || line.trim().is_empty() {
                continue;
            }
            let bad = || PkiError::BadFile {
                path: path.clone(),
                reason: format!(
                    "line {}: expected serial, kind, name, expiry, revocation",
                    number + 1
                ),
            };
            let fields: Vec<&str> = line.split('\t').collect();
            let [serial, kind, name, not_after, revoked] = fields[..] else {
                return Err(bad());
            };
            entries.push(Issued {
                serial: serial.to_owned(),
                kind: match kind {
                    "edge" => IssuedKind::Edge,
                    "server" => IssuedKind::Server,
                    _ => return Err(bad()),
                },
                name: name.to_owned(),
                not_after: not_after.parse().map_err(|_| bad())?,
                revoked: match revoked {
                    "-" => None,
                    t => Some(t.parse().map_err(|_| bad())?),
                },
            });
        }
        Ok(Ledger { entries })
    }

    fn save(&self, layout: &Layout) -> Result<(), PkiError> {
        let mut text = String::from(Self::HEADER);
        for e in &self.entries {
            let kind = match e.kind {
                IssuedKind::Edge => "edge",
                IssuedKind::Server => "server",
            };
            let revoked = e.revoked.map_or_else(|| "-".to_owned(), |t| t.to_string());
            text.push_str(&format!(
                "{}\t{kind}\t{}\t{}\t{revoked}\n",
                e.serial, e.name, e.not_after
            ));
        }
        write_file(&layout.issued(), text.as_bytes(), CERT_MODE, true)
    }

    /// Records the certificate in `name`'s bundle if the ledger does not know its serial.
    fn adopt_bundle(&mut self, layout: &Layout, name: &str) -> Result<(), PkiError> {
        let path = layout.edge_cert(name);
        if !path.exists() {
            return Ok(());
        }
        let issued = issued_from_file(&path, IssuedKind::Edge, name)?;
        if !self.entries.iter().any(|e| e.serial == issued.serial) {
            self.entries.push(issued);
        }
        Ok(())
    }

    /// Marks every unrevoked certificate of edge `name` revoked at `now`; returns their serials.
    fn revoke_edge(&mut self, name: &str, now: SystemTime) -> Vec<String> {
        let at = unix_seconds(now);
        self.entries
            .iter_mut()
            .filter(|e| e.kind == IssuedKind::Edge && e.name == name && e.revoked.is_none())
            .map(|e| {
                e.revoked = Some(at);
                e.serial.clone()
            })
            .collect()
    }
}

fn unix_seconds(t: SystemTime) -> i64 {
    match t.duration_since(SystemTime::UNIX_EPOCH) {
        Ok(d) => i64::try_from(d.as_secs()).unwrap_or(i64::MAX),
        Err(e) => i64::try_from(e.duration().as_secs()).map_or(i64::MIN, |s| -s),
    }
}

fn datetime(t: SystemTime) -> OffsetDateTime {
    OffsetDateTime::from(t)
}

/// `now + days`, as the certificate's notAfter.
fn expiry(now: SystemTime, days: u32) -> OffsetDateTime {
    datetime(now + Duration::from_secs(u64::from(days) * 86_400))
}

/// Certificates start in 1975 (see the module docs: the Pi's clock may be far behind).
fn not_before() -> OffsetDateTime {
    rcgen::date_time_ymd(1975, 1, 1)
}

/// The ledger line of a signed certificate.
fn issued_from_der(
    der: &[u8],
    kind: IssuedKind,
    name: &str,
    path: &Path,
) -> Result<Issued, PkiError> {
    let (_, x509) = x509_parser::parse_x509_certificate(der).map_err(|e| PkiError::BadFile {
        path: path.to_path_buf(),
        reason: format!("unparsable certificate: {e}"),
    })?;
    Ok(Issued {
        serial: hex(x509.raw_serial()),
        kind,
        name: name.to_owned(),
        not_after: x509.validity().not_after.timestamp(),
        revoked: None,
    })
}

fn issued_from_file(path: &Path, kind: IssuedKind, name: &str) -> Result<Issued, PkiError> {
    let pem = read_to_string(path)?;
    let der = CertificateDer::from_pem_slice(pem.as_bytes()).map_err(|e| PkiError::BadFile {
        path: path.to_path_buf(),
        reason: format!("no PEM certificate: {e}"),
    })?;
    issued_from_der(&der, kind, name, path)
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn unhex(text: &str) -> Option<Vec<u8>> {
    if !text.len().is_multiple_of(2) {
        return None;
    }
    (0..text.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(text.get(i..i + 2)?, 16).ok())
        .collect()
}

/// Signs `DIR/crl.pem` listing every revoked serial of the ledger. Its number is the issue time
/// in nanoseconds (increasing from one list to the next); its next update is set ten years out
/// and not enforced by the server (the list is replaced whenever something is revoked).
fn write_crl(layout: &Layout, ca: &Ca, ledger: &Ledger, now: SystemTime) -> Result<(), PkiError> {
    let gen_err = |source| PkiError::Generate {
        what: "revocation list",
        source,
    };
    let mut revoked_certs = Vec::new();
    for e in ledger.entries.iter() {
        let Some(at) = e.revoked else { continue };
        let serial = unhex(&e.serial).ok_or_else(|| PkiError::BadFile {
            path: layout.issued(),
            reason: format!("serial {:?} is not hex", e.serial),
        })?;
        revoked_certs.push(RevokedCertParams {
            serial_number: SerialNumber::from_slice(&serial),
            revocation_time: OffsetDateTime::from_unix_timestamp(at)
                .unwrap_or(OffsetDateTime::UNIX_EPOCH),
            reason_code: Some(RevocationReason::Superseded),
            invalidity_date: None,
        });
    }
    let nanos = now
        .duration_since(SystemTime::UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX));
    let params = CertificateRevocationListParams {
        this_update: datetime(now),
        next_update: expiry(now, 3650),
        crl_number: SerialNumber::from(nanos),
        issuing_distribution_point: None,
        revoked_certs,
        key_identifier_method: KeyIdMethod::Sha256,
    };
    let crl = params.signed_by(&ca.issuer).map_err(gen_err)?;
    let pem = crl.pem().map_err(gen_err)?;
    write_file(&layout.crl(), pem.as_bytes(), CERT_MODE, true)
}

/// The loaded CA: its certificate (PEM, copied into bundles) and the issuer that signs leaves.
struct Ca {
    cert_pem: String,
    issuer: Issuer<'static, KeyPair>,
}

fn checked_server_names(names: &[String]) -> Result<Vec<String>, PkiError> {
    let mut out: Vec<String> = Vec::new();
    for name in names {
        if ServerName::try_from(name.as_str()).is_err() {
            return Err(PkiError::InvalidServerName { name: name.clone() });
        }
        if !out.contains(name) {
            out.push(name.clone());
        }
    }
    Ok(out)
}

fn ensure_ca(
    layout: &Layout,
    validity: Validity,
    now: SystemTime,
) -> Result<(Ca, Provenance), PkiError> {
    let (cert_path, key_path) = (layout.ca_cert(), layout.ca_key());
    match (cert_path.exists(), key_path.exists()) {
        (true, true) => Ok((load_ca(&cert_path, &key_path)?, Provenance::Reused)),
        (false, false) => Ok((
            create_ca(&cert_path, &key_path, validity, now)?,
            Provenance::Created,
        )),
        (true, false) => Err(PkiError::IncompleteCa {
            present: cert_path,
            missing: key_path,
        }),
        (false, true) => Err(PkiError::IncompleteCa {
            present: key_path,
            missing: cert_path,
        }),
    }
}

fn create_ca(
    cert_path: &Path,
    key_path: &Path,
    validity: Validity,
    now: SystemTime,
) -> Result<Ca, PkiError> {
    let gen_err = |source| PkiError::Generate { what: "CA", source };
    let key = KeyPair::generate().map_err(gen_err)?;
    let mut params = CertificateParams::default();
    params.not_before = not_before();
    params.not_after = expiry(now, validity.ca_days);
    // A CN unique to this CA (derived from its key), so a certificate from another scan3d CA
    // is reported as "unknown issuer" rather than as a bad signature.
    let key_id = params.key_identifier(&key);
    let short_id: String = key_id.iter().take(4).map(|b| format!("{b:02x}")).collect();
    let mut dn = DistinguishedName::new();
    dn.push(DnType::OrganizationName, "scan3d");
    dn.push(DnType::CommonName, format!("scan3d pairing CA {short_id}"));
    params.distinguished_name = dn;
    params.is_ca = IsCa::Ca(BasicConstraints::Constrained(0));
    params.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::CrlSign];
    let cert = params.self_signed(&key).map_err(gen_err)?;
    // Key first: a `ca.pem` without its key is reported as an incomplete CA, never reused.
    write_file(key_path, key.serialize_pem().as_bytes(), KEY_MODE, false)?;
    write_file(cert_path, cert.pem().as_bytes(), CERT_MODE, false)?;
    Ok(Ca {
        cert_pem: cert.pem(),
        issuer: Issuer::new(params, key),
    })
}

fn load_ca(cert_path: &Path, key_path: &Path) -> Result<Ca, PkiError> {
    check_key_mode(key_path).map_err(PkiError::Key)?;
    let cert_pem = read_to_string(cert_path)?;
    let key_pem = read_to_string(key_path)?;
    let key = KeyPair::from_pem(&key_pem).map_err(|e| PkiError::BadFile {
        path: key_path.to_path_buf(),
        reason: format!("not a private key: {e}"),
    })?;
    let der =
        CertificateDer::from_pem_slice(cert_pem.as_bytes()).map_err(|e| PkiError::BadFile {
            path: cert_path.to_path_buf(),
            reason: format!("no PEM certificate: {e}"),
        })?;
    let (_, x509) = x509_parser::parse_x509_certificate(&der).map_err(|e| PkiError::BadFile {
        path: cert_path.to_path_buf(),
        reason: format!("unparsable certificate: {e}"),
    })?;
    if !x509.is_ca() {
        return Err(PkiError::BadFile {
            path: cert_path.to_path_buf(),
            reason: "not a CA certificate".to_owned(),
        });
    }
    if x509.public_key().subject_public_key.data.as_ref() != key.public_key_raw() {
        return Err(PkiError::CaKeyMismatch {
            cert: cert_path.to_path_buf(),
            key: key_path.to_path_buf(),
        });
    }
    let issuer = Issuer::from_ca_cert_der(&der, key).map_err(|e| PkiError::BadFile {
        path: cert_path.to_path_buf(),
        reason: format!("unusable CA certificate: {e}"),
    })?;
    Ok(Ca { cert_pem, issuer })
}

fn write_server_cert(
    layout: &Layout,
    ca: &Ca,
    names: &[String],
    validity: Validity,
    now: SystemTime,
) -> Result<Issued, PkiError> {
    let gen_err = |source| PkiError::Generate {
        what: "server certificate",
        source,
    };
    let key = KeyPair::generate().map_err(gen_err)?;
    let mut params = CertificateParams::new(names.to_vec()).map_err(gen_err)?;
    let mut dn = DistinguishedName::new();
    dn.push(DnType::OrganizationName, "scan3d");
    dn.push(DnType::CommonName, "scan3d server");
    params.distinguished_name = dn;
    params.not_before = not_before();
    params.not_after = expiry(now, validity.leaf_days);
    params.extended_key_usages = vec![ExtendedKeyUsagePurpose::ServerAuth];
    params.key_usages = vec![KeyUsagePurpose::DigitalSignature];
    params.use_authority_key_identifier_extension = true;
    let cert = params.signed_by(&key, &ca.issuer).map_err(gen_err)?;
    make_dir(&layout.server_dir())?;
    write_file(
        &layout.server_key(),
        key.serialize_pem().as_bytes(),
        KEY_MODE,
        true,
    )?;
    write_file(
        &layout.server_cert(),
        cert.pem().as_bytes(),
        CERT_MODE,
        true,
    )?;
    issued_from_der(
        cert.der(),
        IssuedKind::Server,
        "server",
        &layout.server_cert(),
    )
}

fn write_edge_bundle(
    layout: &Layout,
    ca: &Ca,
    name: &str,
    validity: Validity,
    now: SystemTime,
) -> Result<Issued, PkiError> {
    let gen_err = |source| PkiError::Generate {
        what: "edge certificate",
        source,
    };
    let key = KeyPair::generate().map_err(gen_err)?;
    let mut params = CertificateParams::new(vec![name.to_owned()]).map_err(gen_err)?;
    let mut dn = DistinguishedName::new();
    dn.push(DnType::OrganizationName, "scan3d");
    dn.push(DnType::CommonName, name);
    params.distinguished_name = dn;
    params.not_before = not_before();
    params.not_after = expiry(now, validity.leaf_days);
    params.extended_key_usages = vec![ExtendedKeyUsagePurpose::ClientAuth];
    params.key_usages = vec![KeyUsagePurpose::DigitalSignature];
    params.use_authority_key_identifier_extension = true;
    let cert = params.signed_by(&key, &ca.issuer).map_err(gen_err)?;
    make_dir(&layout.edge_dir(name))?;
    write_file(
        &layout.edge_key(name),
        key.serialize_pem().as_bytes(),
        KEY_MODE,
        true,
    )?;
    write_file(
        &layout.edge_cert(name),
        cert.pem().as_bytes(),
        CERT_MODE,
        true,
    )?;
    write_file(
        &layout.edge_ca_cert(name),
        ca.cert_pem.as_bytes(),
        CERT_MODE,
        true,
    )?;
    issued_from_der(cert.der(), IssuedKind::Edge, name, &layout.edge_cert(name))
}

/// The DNS and IP SANs of a certificate file, as text.
fn read_san_names(path: &Path) -> Result<Vec<String>, PkiError> {
    let bad = |reason: String| PkiError::BadFile {
        path: path.to_path_buf(),
        reason,
    };
    let pem = read_to_string(path)?;
    let der = CertificateDer::from_pem_slice(pem.as_bytes())
        .map_err(|e| bad(format!("no PEM certificate: {e}")))?;
    let (_, x509) = x509_parser::parse_x509_certificate(&der)
        .map_err(|e| bad(format!("unparsable certificate: {e}")))?;
    let san = x509
        .subject_alternative_name()
        .map_err(|e| bad(format!("bad subjectAltName: {e}")))?;
    let mut names = Vec::new();
    for general in san.iter().flat_map(|ext| ext.value.general_names.iter()) {
        match general {
            x509_parser::extensions::GeneralName::DNSName(dns) => names.push(dns.to_string()),
            x509_parser::extensions::GeneralName::IPAddress(bytes) => {
                let ip = match bytes.len() {
                    4 => <[u8; 4]>::try_from(*bytes).ok().map(IpAddr::from),
                    16 => <[u8; 16]>::try_from(*bytes).ok().map(IpAddr::from),
                    _ => None,
                };
                if let Some(ip) = ip {
                    names.push(ip.to_string());
                }
            }
            _ => {}
        }
    }
    Ok(names)
}

fn read_to_string(path: &Path) -> Result<String, PkiError> {
    fs::read_to_string(path).map_err(|source| PkiError::Io {
        path: path.to_path_buf(),
        source,
    })
}

fn make_dir(path: &Path) -> Result<(), PkiError> {
    DirBuilder::new()
        .recursive(true)
        .mode(DIR_MODE)
        .create(path)
        .map_err(|source| PkiError::Io {
            path: path.to_path_buf(),
            source,
        })
}

/// Writes `contents` to `path`, created with `mode`, through a temporary file in the same
/// directory. `replace = false` never touches an existing `path` (the CA).
fn write_file(path: &Path, contents: &[u8], mode: u32, replace: bool) -> Result<(), PkiError> {
    let io_err = |path: &Path| {
        let path = path.to_path_buf();
        move |source| PkiError::Io { path, source }
    };
    let (Some(dir), Some(name)) = (path.parent(), path.file_name()) else {
        return Err(PkiError::Io {
            path: path.to_path_buf(),
            source: io::Error::new(io::ErrorKind::InvalidInput, "not a file path"),
        });
    };
    let tmp = dir.join(format!(".{}.tmp", name.to_string_lossy()));
    match fs::remove_file(&tmp) {
        Err(e) if e.kind() != io::ErrorKind::NotFound => return Err(io_err(&tmp)(e)),
        _ => {}
    }
    let mut file = OpenOptions::new()
        .write(true)
        .create_new(true)
        .mode(mode)
        .open(&tmp)
        .map_err(io_err(&tmp))?;
    file.write_all(contents).map_err(io_err(&tmp))?;
    file.sync_all().map_err(io_err(&tmp))?;
    drop(file);
    let published = if replace {
        fs::rename(&tmp, path)
    } else {
        // A hard link fails if `path` exists: no clobbering, even against a concurrent run.
        fs::hard_link(&tmp, path).and_then(|()| fs::remove_file(&tmp))
    };
    if let Err(e) = published {
        let _ = fs::remove_file(&tmp);
        return Err(io_err(path)(e));
    }
    File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(io_err(dir))
}

#[cfg(test)]
mod tests {
    use std::os::unix::fs::PermissionsExt;

    use super::*;

    fn request(dir: &Path, edge: &str) -> PairRequest {
        PairRequest {
            dir: dir.to_path_buf(),
            edge: edge.to_owned(),
            server_names: vec![],
            force: false,
        }
    }

    fn mode(path: &Path) -> u32 {
        fs::metadata(path).unwrap().permissions().mode() & 0o777
    }

    fn cert_der(path: &Path) -> CertificateDer<'static> {
        CertificateDer::from_pem_file(path).unwrap()
    }

    fn common_name(der: &CertificateDer<'_>) -> String {
        let (_, x509) = x509_parser::parse_x509_certificate(der).unwrap();
        let cn = x509.subject().iter_common_name().next().unwrap();
        cn.as_str().unwrap().to_owned()
    }

    #[test]
    fn first_run_creates_ca_server_and_bundle() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("pki");
        let out = pair(&request(&dir, "pi-01")).unwrap();
        let layout = Layout::new(&dir);
        assert_eq!(out.ca, Provenance::Created);
        assert_eq!(out.server, Provenance::Created);
        assert_eq!(out.edge, Provenance::Created);
        assert_eq!(out.server_names, ["localhost", "127.0.0.1"]);
        assert_eq!(out.edge_dir, dir.join("edges").join("pi-01"));
        for path in [
            dir.join("ca.pem"),
            dir.join("ca.key"),
            dir.join("server/server.pem"),
            dir.join("server/server.key"),
            dir.join("edges/pi-01/edge.pem"),
            dir.join("edges/pi-01/edge.key"),
            dir.join("edges/pi-01/ca.pem"),
        ] {
            assert!(path.is_file(), "{} missing", path.display());
        }
        // The bundle's CA is a byte-for-byte copy of the CA.
        assert_eq!(
            fs::read(layout.ca_cert()).unwrap(),
            fs::read(layout.edge_ca_cert("pi-01")).unwrap()
        );
        // No temporary files left behind.
        let leftovers: Vec<_> = fs::read_dir(layout.edge_dir("pi-01"))
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .filter(|n| n.to_string_lossy().starts_with('.'))
            .collect();
        assert!(leftovers.is_empty(), "{leftovers:?}");
    }

    #[test]
    fn certificates_carry_the_right_names_and_usages() {
        let tmp = tempfile::tempdir().unwrap();
        let mut req = request(tmp.path(), "lab_pi-02.b");
        req.server_names = vec!["scan.example.org".into(), "192.168.1.20".into()];
        let out = pair(&req).unwrap();
        assert_eq!(out.server_names, ["scan.example.org", "192.168.1.20"]);
        let layout = Layout::new(tmp.path());

        let edge = cert_der(&layout.edge_cert("lab_pi-02.b"));
        let (_, x509) = x509_parser::parse_x509_certificate(&edge).unwrap();
        assert_eq!(common_name(&edge), "lab_pi-02.b");
        let eku = x509.extended_key_usage().unwrap().unwrap().value;
        assert!(eku.client_auth && !eku.server_auth);
        assert_eq!(
            read_san_names(&layout.edge_cert("lab_pi-02.b")).unwrap(),
            ["lab_pi-02.b"]
        );

        let server = cert_der(&layout.server_cert());
        let (_, x509) = x509_parser::parse_x509_certificate(&server).unwrap();
        let eku = x509.extended_key_usage().unwrap().unwrap().value;
        assert!(eku.server_auth && !eku.client_auth);
        let san = x509.subject_alternative_name().unwrap().unwrap().value;
        use x509_parser::extensions::GeneralName;
        assert_eq!(
            san.general_names,
            [
                GeneralName::DNSName("scan.example.org"),
                GeneralName::IPAddress(&[192, 168, 1, 20]),
            ]
        );

        let ca = cert_der(&layout.ca_cert());
        let (_, x509) = x509_parser::parse_x509_certificate(&ca).unwrap();
        assert!(x509.is_ca());
    }

    #[test]
    fn second_edge_reuses_the_ca_and_keeps_the_server_certificate() {
        let tmp = tempfile::tempdir().unwrap();
        let layout = Layout::new(tmp.path());
        let mut first = request(tmp.path(), "pi-01");
        first.server_names = vec!["scanhost".into()];
        pair(&first).unwrap();
        let ca_pem = fs::read(layout.ca_cert()).unwrap();
        let ca_key = fs::read(layout.ca_key()).unwrap();
        let server_pem = fs::read(layout.server_cert()).unwrap();

        let out = pair(&request(tmp.path(), "pi-02")).unwrap();
        assert_eq!(out.ca, Provenance::Reused);
        assert_eq!(out.server, Provenance::Reused);
        assert_eq!(out.server_names, ["scanhost"]);
        assert_eq!(fs::read(layout.ca_cert()).unwrap(), ca_pem);
        assert_eq!(fs::read(layout.ca_key()).unwrap(), ca_key);
        assert_eq!(fs::read(layout.server_cert()).unwrap(), server_pem);
        assert_eq!(fs::read(layout.edge_ca_cert("pi-02")).unwrap(), ca_pem);

        // Both edges are signed by the one CA: same issuer, verified signature.
        let ca_der = cert_der(&layout.ca_cert());
        let (_, ca) = x509_parser::parse_x509_certificate(&ca_der).unwrap();
        for edge in ["pi-01", "pi-02"] {
            let der = cert_der(&layout.edge_cert(edge));
            let (_, leaf) = x509_parser::parse_x509_certificate(&der).unwrap();
            assert_eq!(leaf.issuer(), ca.subject());
            leaf.verify_signature(Some(ca.public_key())).unwrap();
        }

        // New server names re-issue the server certificate under the same CA.
        let mut third = request(tmp.path(), "pi-03");
        third.server_names = vec!["10.0.0.5".into()];
        let out = pair(&third).unwrap();
        assert_eq!(out.ca, Provenance::Reused);
        assert_eq!(out.server, Provenance::Replaced);
        assert_ne!(fs::read(layout.server_cert()).unwrap(), server_pem);
        assert_eq!(read_san_names(&layout.server_cert()).unwrap(), ["10.0.0.5"]);
    }

    #[test]
    fn keys_are_private_and_directories_closed() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("pki");
        pair(&request(&dir, "pi-01")).unwrap();
        let layout = Layout::new(&dir);
        for key in [
            layout.ca_key(),
            layout.server_key(),
            layout.edge_key("pi-01"),
        ] {
            assert_eq!(mode(&key), 0o600, "{}", key.display());
        }
        for d in [
            dir.clone(),
            layout.server_dir(),
            dir.join("edges"),
            layout.edge_dir("pi-01"),
        ] {
            assert_eq!(mode(&d), 0o700, "{}", d.display());
        }
        // Still 0600 after a forced replacement.
        let mut again = request(&dir, "pi-01");
        again.force = true;
        again.server_names = vec!["localhost".into()];
        pair(&again).unwrap();
        assert_eq!(mode(&layout.edge_key("pi-01")), 0o600);
        assert_eq!(mode(&layout.server_key()), 0o600);
    }

    #[test]
    fn an_existing_bundle_is_refused_without_force() {
        let tmp = tempfile::tempdir().unwrap();
        let layout = Layout::new(tmp.path());
        pair(&request(tmp.path(), "pi-01")).unwrap();
        let key = fs::read(layout.edge_key("pi-01")).unwrap();

        let err = pair(&request(tmp.path(), "pi-01")).unwrap_err();
        assert!(matches!(&err, PkiError::BundleExists { dir } if *dir == layout.edge_dir("pi-01")));
        assert!(err.to_string().contains("--force"), "{err}");
        assert_eq!(fs::read(layout.edge_key("pi-01")).unwrap(), key);

        let mut forced = request(tmp.path(), "pi-01");
        forced.force = true;
        let out = pair(&forced).unwrap();
        assert_eq!(out.edge, Provenance::Replaced);
        assert_eq!(out.ca, Provenance::Reused);
        assert_ne!(fs::read(layout.edge_key("pi-01")).unwrap(), key);
    }

    #[test]
    fn bad_names_are_rejected_before_anything_is_written() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("pki");
        let long = "a".repeat(64);
        for name in [
            "",
            ".hidden",
            "..",
            "a/b",
            "pi 01",
            "pi\u{e9}",
            "x\0",
            long.as_str(),
        ] {
            let err = pair(&request(&dir, name)).unwrap_err();
            assert!(
                matches!(&err, PkiError::InvalidEdgeName { name: n, .. } if n == name),
                "{name:?}: {err}"
            );
        }
        let mut bad_server = request(&dir, "pi-01");
        bad_server.server_names = vec!["bad host".into()];
        assert!(matches!(
            pair(&bad_server),
            Err(PkiError::InvalidServerName { .. })
        ));
        assert!(!dir.exists());
        for name in ["a", "pi-01", "Lab_Pi.2", &"z".repeat(63)] {
            assert!(validate_edge_name(name).is_ok(), "{name}");
        }
    }

    #[test]
    fn a_half_present_or_mismatched_ca_is_reported() {
        let tmp = tempfile::tempdir().unwrap();
        let layout = Layout::new(tmp.path());
        pair(&request(tmp.path(), "pi-01")).unwrap();

        // ca.key of another CA.
        let other = tempfile::tempdir().unwrap();
        pair(&request(other.path(), "pi-01")).unwrap();
        let own_key = fs::read(layout.ca_key()).unwrap();
        fs::copy(Layout::new(other.path()).ca_key(), layout.ca_key()).unwrap();
        let err = pair(&request(tmp.path(), "pi-02")).unwrap_err();
        assert!(matches!(err, PkiError::CaKeyMismatch { .. }), "{err}");

        // ca.key missing: never silently replaced by a new CA.
        fs::write(layout.ca_key(), own_key).unwrap();
        fs::remove_file(layout.ca_key()).unwrap();
        let err = pair(&request(tmp.path(), "pi-02")).unwrap_err();
        assert!(
            matches!(&err, PkiError::IncompleteCa { missing, .. } if *missing == layout.ca_key()),
            "{err}"
        );
        assert!(err.to_string().contains("ca.key"));
    }

    fn crl_serials(layout: &Layout) -> Vec<String> {
        let der = CertificateRevocationListDer::from_pem_file(layout.crl()).unwrap();
        let (_, crl) = x509_parser::parse_x509_crl(&der).unwrap();
        crl.iter_revoked_certificates()
            .map(|r| hex(r.raw_serial()))
            .collect()
    }

    fn serial_of(path: &Path) -> String {
        let der = cert_der(path);
        let (_, x509) = x509_parser::parse_x509_certificate(&der).unwrap();
        hex(x509.raw_serial())
    }

    #[test]
    fn certificates_expire_after_the_chosen_validity() {
        let tmp = tempfile::tempdir().unwrap();
        let now = SystemTime::UNIX_EPOCH + Duration::from_secs(1_800_000_000);
        let validity = Validity {
            leaf_days: 30,
            ca_days: 400,
        };
        pair_with(&request(tmp.path(), "pi-01"), validity, now).unwrap();
        let layout = Layout::new(tmp.path());
        let not_after = |path: &Path| {
            let der = cert_der(path);
            let (_, x509) = x509_parser::parse_x509_certificate(&der).unwrap();
            (
                x509.validity().not_before.timestamp(),
                x509.validity().not_after.timestamp(),
            )
        };
        let start_1975 = 157_766_400;
        assert_eq!(
            not_after(&layout.edge_cert("pi-01")),
            (start_1975, 1_800_000_000 + 30 * 86_400)
        );
        assert_eq!(
            not_after(&layout.server_cert()),
            (start_1975, 1_800_000_000 + 30 * 86_400)
        );
        assert_eq!(
            not_after(&layout.ca_cert()),
            (start_1975, 1_800_000_000 + 400 * 86_400)
        );
        for days in [0, Validity::MAX_DAYS + 1] {
            let bad = Validity {
                leaf_days: days,
                ..validity
            };
            let err = pair_with(&request(tmp.path(), "pi-02"), bad, now).unwrap_err();
            assert!(matches!(err, PkiError::BadValidity { .. }), "{err}");
        }
    }

    #[test]
    fn revocation_lists_every_serial_issued_to_the_edge_and_only_those() {
        let tmp = tempfile::tempdir().unwrap();
        let layout = Layout::new(tmp.path());
        pair(&request(tmp.path(), "pi-01")).unwrap();
        pair(&request(tmp.path(), "pi-02")).unwrap();
        assert!(
            crl_serials(&layout).is_empty(),
            "a fresh CA's list is empty"
        );
        let first = serial_of(&layout.edge_cert("pi-01"));
        let mut forced = request(tmp.path(), "pi-01");
        forced.force = true;
        let out = pair(&forced).unwrap();
        assert_eq!(out.revoked, std::slice::from_ref(&first));
        let second = serial_of(&layout.edge_cert("pi-01"));
        assert_ne!(first, second);
        assert_eq!(crl_serials(&layout), std::slice::from_ref(&first));

        let out = revoke(tmp.path(), "pi-01", SystemTime::now()).unwrap();
        assert_eq!(out.revoked, std::slice::from_ref(&second));
        assert_eq!(crl_serials(&layout), [first, second]);
        // Nothing left to revoke; pi-02 never listed.
        assert!(
            revoke(tmp.path(), "pi-01", SystemTime::now())
                .unwrap()
                .revoked
                .is_empty()
        );
        assert!(!crl_serials(&layout).contains(&serial_of(&layout.edge_cert("pi-02"))));
        let ledger = fs::read_to_string(layout.issued()).unwrap();
        assert_eq!(
            ledger
                .lines()
                .filter(|l| l.contains("\tedge\tpi-01\t"))
                .count(),
            2
        );
        assert!(matches!(
            revoke(tmp.path(), "pi-09", SystemTime::now()),
            Err(PkiError::UnknownEdge { .. })
        ));
        assert!(matches!(
            renew(
                tmp.path(),
                "pi-09",
                &[],
                Validity::default(),
                SystemTime::now()
            ),
            Err(PkiError::UnknownEdge { .. })
        ));
    }

    #[test]
    fn a_bundle_from_before_the_ledger_is_still_revoked() {
        let tmp = tempfile::tempdir().unwrap();
        let layout = Layout::new(tmp.path());
        pair(&request(tmp.path(), "pi-01")).unwrap();
        let serial = serial_of(&layout.edge_cert("pi-01"));
        fs::remove_file(layout.issued()).unwrap();
        fs::remove_file(layout.crl()).unwrap();
        assert_eq!(
            revoke(tmp.path(), "pi-01", SystemTime::now())
                .unwrap()
                .revoked,
            std::slice::from_ref(&serial)
        );
        assert_eq!(crl_serials(&layout), [serial]);
    }

    #[test]
    fn a_ca_key_readable_by_others_is_refused() {
        let tmp = tempfile::tempdir().unwrap();
        let layout = Layout::new(tmp.path());
        pair(&request(tmp.path(), "pi-01")).unwrap();
        fs::set_permissions(layout.ca_key(), fs::Permissions::from_mode(0o644)).unwrap();
        let err = pair(&request(tmp.path(), "pi-02")).unwrap_err();
        assert!(
            matches!(err, PkiError::Key(PemError::KeyTooOpen { mode: 0o644, .. })),
            "{err}"
        );
        assert!(err.to_string().contains("ca.key"), "{err}");
        assert!(!layout.edge_dir("pi-02").exists());
        let err = revoke(tmp.path(), "pi-01", SystemTime::now()).unwrap_err();
        assert!(matches!(err, PkiError::Key(_)), "{err}");
    }
}
