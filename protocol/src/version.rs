//! Protocol version and the compatibility rule.

/// The protocol version this build speaks; written in every frame header and in [`crate::Hello`].
///
/// Bump it for any change to the header, to a field, or to the order of enum variants.
///
/// | version | change |
/// | --- | --- |
/// | 1 | first release |
/// | 2 | one sample timeline (static-scan yaws refer to the Sweep revolution's samples instead of repeating them), the edge's clock identity in `Hello`, time sync on QUIC datagrams |
pub const PROTOCOL_VERSION: u16 = 2;

/// The peer speaks a protocol version this build cannot read.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("peer speaks protocol version {peer}, this build speaks version {supported}")]
pub struct IncompatibleVersion {
    /// The peer's version.
    pub peer: u16,
    /// The version this build speaks ([`PROTOCOL_VERSION`]).
    pub supported: u16,
}

/// Whether a peer speaking protocol version `peer` can talk to this build.
///
/// The rule is an exact match: postcard has no field tags, so any layout change is incompatible
/// in both directions.
pub fn check_compatible(peer: u16) -> Result<(), IncompatibleVersion> {
    if peer == PROTOCOL_VERSION {
        Ok(())
    } else {
        Err(IncompatibleVersion {
            peer,
            supported: PROTOCOL_VERSION,
        })
    }
}
