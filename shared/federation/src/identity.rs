//! A volunteer's identity: an Ed25519 key pair it keeps (a browser in IndexedDB, a native volunteer in a file under
//! its config directory), and the proof it gives on every connection, a signature over the server's fresh
//! challenge, its name and the protocol version ([`ClientMessage::Identify`](crate::ClientMessage::Identify)).
//! The server binds shards, per-client strategy state and upload rights to the public key, not the name, so a name
//! alone takes nothing from the volunteer who holds it.

use ed25519_dalek::{Signature, Signer, SigningKey, VerifyingKey};

use crate::protocol::PROTOCOL_VERSION;

/// Bytes of a key pair's secret seed, of a public key, and of a challenge's nonce.
pub const SEED_BYTES: usize = 32;
pub const PUBLIC_KEY_BYTES: usize = 32;
pub const NONCE_BYTES: usize = 32;

/// Why a key or a proof was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum IdentityError {
    #[error("{what}: expected {expected} hex bytes, got {got:?}")]
    Hex { what: &'static str, expected: usize, got: String },
    #[error("the public key is not a valid Ed25519 point")]
    PublicKey,
    #[error("the signature does not verify against the public key")]
    Signature,
}

/// A volunteer's key pair.
pub struct Identity {
    key: SigningKey,
}

impl Identity {
    /// The key pair of a 32-byte secret seed (from the OS's or the browser's random source).
    pub fn from_seed(seed: [u8; SEED_BYTES]) -> Self {
        Self { key: SigningKey::from_bytes(&seed) }
    }

    /// The key pair of a seed written as [`Identity::seed_hex`] writes it.
    pub fn from_seed_hex(hex: &str) -> Result<Self, IdentityError> {
        Ok(Self::from_seed(from_hex("secret key seed", hex.trim())?))
    }

    /// The secret seed in hex, to keep.
    pub fn seed_hex(&self) -> String {
        to_hex(&self.key.to_bytes())
    }

    /// The public key in hex: what the server knows the volunteer by.
    pub fn public_key_hex(&self) -> String {
        to_hex(self.key.verifying_key().as_bytes())
    }

    /// The signature (hex) proving this key answers `nonce_hex` as volunteer `name`.
    pub fn prove(&self, nonce_hex: &str, name: &str) -> String {
        to_hex(&self.key.sign(&signed_message(nonce_hex, name)).to_bytes())
    }
}

impl std::fmt::Debug for Identity {
    /// The public key only: the seed never reaches a log.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Identity({})", self.public_key_hex())
    }
}

/// Checks that `signature_hex` is `public_key_hex`'s answer to `nonce_hex` as `name` (strict verification: no
/// malleable or small-order forms), and returns the public key's bytes.
pub fn verify_proof(
    public_key_hex: &str,
    signature_hex: &str,
    nonce_hex: &str,
    name: &str,
) -> Result<[u8; PUBLIC_KEY_BYTES], IdentityError> {
    let public: [u8; PUBLIC_KEY_BYTES] = from_hex("public key", public_key_hex)?;
    let signature: [u8; 64] = from_hex("signature", signature_hex)?;
    let key = VerifyingKey::from_bytes(&public).map_err(|_| IdentityError::PublicKey)?;
    key.verify_strict(&signed_message(nonce_hex, name), &Signature::from_bytes(&signature))
        .map_err(|_| IdentityError::Signature)?;
    Ok(public)
}

/// What a volunteer signs: a domain tag (a signature for anything else never passes for a join), the protocol
/// version, the challenge and the name, each length-prefixed so no two inputs share a message.
fn signed_message(nonce_hex: &str, name: &str) -> Vec<u8> {
    let mut message = b"fedvla identify\0".to_vec();
    message.extend_from_slice(&PROTOCOL_VERSION.to_le_bytes());
    for part in [nonce_hex, name] {
        message.extend_from_slice(&(part.len() as u64).to_le_bytes());
        message.extend_from_slice(part.as_bytes());
    }
    message
}

/// Lowercase hex of `bytes`.
pub fn to_hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// Exactly `N` bytes from their hex (either case).
pub fn from_hex<const N: usize>(what: &'static str, hex: &str) -> Result<[u8; N], IdentityError> {
    let refused = || IdentityError::Hex { what, expected: N, got: hex.chars().take(2 * N + 2).collect() };
    if hex.len() != 2 * N || !hex.is_ascii() {
        return Err(refused());
    }
    let mut out = [0u8; N];
    for (byte, pair) in out.iter_mut().zip(hex.as_bytes().chunks_exact(2)) {
        let pair = std::str::from_utf8(pair).map_err(|_| refused())?;
        *byte = u8::from_str_radix(pair, 16).map_err(|_| refused())?;
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_proof_verifies_only_for_its_key_nonce_and_name() {
        let alice = Identity::from_seed([7; SEED_BYTES]);
        let mallory = Identity::from_seed([9; SEED_BYTES]);
        let nonce = to_hex(&[1; NONCE_BYTES]);
        let proof = alice.prove(&nonce, "alice");
        let public = verify_proof(&alice.public_key_hex(), &proof, &nonce, "alice").unwrap();
        assert_eq!(to_hex(&public), alice.public_key_hex());
        // Another key, another challenge, another name: refused.
        let other_nonce = to_hex(&[2; NONCE_BYTES]);
        assert_eq!(verify_proof(&mallory.public_key_hex(), &proof, &nonce, "alice"), Err(IdentityError::Signature));
        assert_eq!(verify_proof(&alice.public_key_hex(), &proof, &other_nonce, "alice"), Err(IdentityError::Signature));
        assert_eq!(verify_proof(&alice.public_key_hex(), &proof, &nonce, "alic"), Err(IdentityError::Signature));
        assert!(matches!(verify_proof("zz", &proof, &nonce, "alice"), Err(IdentityError::Hex { .. })));
        // The seed round-trips through its hex, and never shows in Debug.
        let again = Identity::from_seed_hex(&alice.seed_hex()).unwrap();
        assert_eq!(again.public_key_hex(), alice.public_key_hex());
        assert!(!format!("{alice:?}").contains(&alice.seed_hex()));
    }
}
