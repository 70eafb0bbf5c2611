//! The private PKI behind the uplink's mutual TLS: one CA, one server certificate, one bundle
//! per edge (`scan3d pair`).
//!
//! Layout of the PKI directory `DIR` (directories are created `0700`, keys `0600`):
//!
//! ```text
//! DIR/ca.pem                  CA certificate (created on first use, never overwritten)
//! DIR/ca.key                  CA private key (PKCS#8 PEM)
//! DIR/server/server.pem       server certificate; SANs = the server's host names / IPs
//! DIR/server/server.key       server private key
//! DIR/edges/NAME/edge.pem     edge certificate, CN = NAME (also a DNS SAN), EKU clientAuth
//! DIR/edges/NAME/edge.key     edge private key
//! DIR/edges/NAME/ca.pem       copy of DIR/ca.pem, so the bundle is self-contained
//! ```
//!
//! `DIR/edges/NAME` is the bundle to copy to the Pi. The server loads `DIR/ca.pem` and
//! `DIR/server/*` (see [`super::tls::server_config`]) and trusts any client certificate the CA
//! signed; the certificate's CN becomes the edge's identity.
//!
//! Keys are ECDSA P-256. Certificates use rcgen's validity window (1975 to 4096): the Pi has no
//! real-time clock, so certificates must not depend on the date. There is no revocation; to
//! retire every credential, move the whole directory away and pair again. Replacing an edge
//! bundle with `force` issues a new key, but the old certificate stays valid (same CA, same
//! name). Files are written to a temporary name and then moved into place, so a crash never
//! leaves a half-written key.

use std::fs::{self, DirBuilder, File, OpenOptions};
use std::io::{self, Write};
use std::net::IpAddr;
use std::os::unix::fs::{DirBuilderExt, OpenOptionsExt};
use std::path::{Path, PathBuf};

use rcgen::{
    BasicConstraints, CertificateParams, DistinguishedName, DnType, ExtendedKeyUsagePurpose, IsCa,
    Issuer, KeyPair, KeyUsagePurpose,
};
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, ServerName};

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
        "edge bundle {} already exists; pass --force to issue a new one (the old certificate stays valid)",
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
/// edge bundle. Nothing is written when the request is invalid or the bundle exists without
/// `force`.
pub fn pair(req: &PairRequest) -> Result<PairOutcome, PkiError> {
    validate_edge_name(&req.edge)?;
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
    let (ca, ca_status) = ensure_ca(&layout)?;

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
            write_server_cert(&layout, &ca, &names)?;
            let status = if existing_server {
                Provenance::Replaced
            } else {
                Provenance::Created
            };
            (status, names)
        };

    write_edge_bundle(&layout, &ca, &req.edge)?;
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
    })
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

fn ensure_ca(layout: &Layout) -> Result<(Ca, Provenance), PkiError> {
    let (cert_path, key_path) = (layout.ca_cert(), layout.ca_key());
    match (cert_path.exists(), key_path.exists()) {
        (true, true) => Ok((load_ca(&cert_path, &key_path)?, Provenance::Reused)),
        (false, false) => Ok((create_ca(&cert_path, &key_path)?, Provenance::Created)),
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

fn create_ca(cert_path: &Path, key_path: &Path) -> Result<Ca, PkiError> {
    let gen_err = |source| PkiError::Generate { what: "CA", source };
    let key = KeyPair::generate().map_err(gen_err)?;
    let mut params = CertificateParams::default();
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

fn write_server_cert(layout: &Layout, ca: &Ca, names: &[String]) -> Result<(), PkiError> {
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
    )
}

fn write_edge_bundle(layout: &Layout, ca: &Ca, name: &str) -> Result<(), PkiError> {
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
    )
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
}
