//! The sessions of connected clients: the bearer token each connection's admission carries (with the shard bound
//! to the client's key, the only one it may download), the rollout videos each client may still upload for the
//! round that asked it for them (and no other), and the SCAFFOLD correction each may download for its round.

use std::collections::HashMap;
use std::sync::{Arc, Mutex, MutexGuard};

use bytes::Bytes;

/// Session tokens of the connected clients, for their HTTP uploads, and the rollout videos each may upload.
#[derive(Clone, Default)]
pub struct Sessions {
    inner: Arc<Mutex<SessionTable>>,
}

/// Who holds a session.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SessionHolder {
    pub client_id: u64,
    /// The shard bound to the client's key, the one shard it may download.
    pub shard: Option<usize>,
}

#[derive(Default)]
struct SessionTable {
    by_token: HashMap<String, SessionHolder>,
    /// Client id -> (round, videos it may still upload for that round).
    uploads: HashMap<u64, (u64, u32)>,
    /// Client id -> (round, its SCAFFOLD correction for that round, as safetensors).
    corrections: HashMap<u64, (u64, Bytes)>,
}

impl Sessions {
    /// A fresh unguessable token for `client_id`, which may download `shard`.
    pub fn open(&self, client_id: u64, shard: Option<usize>) -> String {
        let token = random_token();
        self.table().by_token.insert(token.clone(), SessionHolder { client_id, shard });
        token
    }

    pub fn close(&self, client_id: u64) {
        let mut table = self.table();
        table.by_token.retain(|_, holder| holder.client_id != client_id);
        table.uploads.remove(&client_id);
        table.corrections.remove(&client_id);
    }

    /// Offers `client_id` its SCAFFOLD correction for `round`.
    pub fn offer_correction(&self, client_id: u64, round: u64, correction: Bytes) {
        self.table().corrections.insert(client_id, (round, correction));
    }

    /// The correction offered to `client_id` for `round`.
    pub fn correction(&self, client_id: u64, round: u64) -> Option<Bytes> {
        self.table().corrections.get(&client_id).filter(|(r, _)| *r == round).map(|(_, bytes)| bytes.clone())
    }

    /// Lets `client_id` upload `videos` rollout videos for `round` (its task asked for that many episodes).
    pub fn allow_uploads(&self, client_id: u64, round: u64, videos: u32) {
        self.table().uploads.insert(client_id, (round, videos));
    }

    /// Ends every upload permission and correction of `round` (it closed).
    pub fn end_uploads(&self, round: u64) {
        let mut table = self.table();
        table.uploads.retain(|_, (r, _)| *r != round);
        table.corrections.retain(|_, (r, _)| *r != round);
    }

    pub fn holder(&self, token: &str) -> Option<SessionHolder> {
        self.table().by_token.get(token).copied()
    }

    /// Takes one of `client_id`'s video uploads for `round`.
    pub fn take_upload(&self, client_id: u64, round: u64) -> Result<(), UploadRefused> {
        match self.table().uploads.get_mut(&client_id) {
            Some((r, left)) if *r == round && *left > 0 => {
                *left -= 1;
                Ok(())
            }
            Some((r, 0)) if *r == round => Err(UploadRefused::AllTaken { client_id, round }),
            _ => Err(UploadRefused::NotAsked { client_id, round }),
        }
    }

    fn table(&self) -> MutexGuard<'_, SessionTable> {
        self.inner.lock().expect("sessions lock")
    }
}

/// Why a video upload was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum UploadRefused {
    #[error("round {round} asked client {client_id} for no rollout videos")]
    NotAsked { client_id: u64, round: u64 },
    #[error("client {client_id} has uploaded every video round {round} asked it for")]
    AllTaken { client_id: u64, round: u64 },
}

/// A fresh token of 128 random bits from the OS, as 32 hex digits.
pub fn random_token() -> String {
    random_hex::<16>()
}

/// `N` fresh random bytes from the OS, in hex (tokens, identity challenges).
pub fn random_hex<const N: usize>() -> String {
    use rand::{Rng, SeedableRng};
    let bytes: [u8; N] = rand::rngs::StdRng::from_os_rng().random();
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// Compares in time independent of where the strings differ, so a token cannot be guessed byte by byte.
pub fn same_secret(a: &str, b: &str) -> bool {
    a.len() == b.len() && a.bytes().zip(b.bytes()).fold(0u8, |diff, (x, y)| diff | (x ^ y)) == 0
}
