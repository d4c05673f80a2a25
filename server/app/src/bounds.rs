//! The bounds on what strangers' input may cost the server beyond the listener's ([`crate::http`]): joins per
//! address per minute ([`JoinLimiter`]), messages per second on one connection ([`MessageRate`]) and the memory
//! held at once for uploads on their way in, updates and rollout videos together ([`UploadBudget`]). Each is a run
//! configuration key; what they refuse is counted on the console.

use std::collections::HashMap;
use std::net::IpAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use tokio::time::Instant;

/// The window joins are counted in.
const JOIN_WINDOW: Duration = Duration::from_secs(60);
/// Addresses whose joins are counted at once. Past it, windows that ended are forgotten; if every one is still
/// open, a new address is let through uncounted: an attacker with that many addresses is past any per-address
/// bound anyway, and the map must not grow with it.
const MAX_TRACKED_ADDRESSES: usize = 65_536;

/// Joins per address per minute (`joins-per-address-per-minute`); cheap to clone.
#[derive(Clone)]
pub struct JoinLimiter {
    per_minute: u32,
    windows: Arc<Mutex<HashMap<IpAddr, JoinWindow>>>,
}

#[derive(Clone, Copy)]
struct JoinWindow {
    started: Instant,
    joins: u32,
}

impl JoinLimiter {
    pub fn new(per_minute: u32) -> Self {
        Self { per_minute, windows: Arc::default() }
    }

    /// Counts a join from `address`; false when that address has joined `per_minute` times in its current minute.
    pub fn allow(&self, address: IpAddr) -> bool {
        let now = Instant::now();
        let mut windows = self.windows.lock().expect("join windows lock");
        if windows.len() >= MAX_TRACKED_ADDRESSES && !windows.contains_key(&address) {
            windows.retain(|_, w| now.duration_since(w.started) < JOIN_WINDOW);
            if windows.len() >= MAX_TRACKED_ADDRESSES {
                return true;
            }
        }
        let window = windows.entry(address).or_insert(JoinWindow { started: now, joins: 0 });
        if now.duration_since(window.started) >= JOIN_WINDOW {
            *window = JoinWindow { started: now, joins: 0 };
        }
        if window.joins >= self.per_minute {
            return false;
        }
        window.joins += 1;
        true
    }
}

/// One connection's messages per second (`max-messages-per-second`): a token bucket that holds one second's
/// worth, so a burst of that many passes and a steady flood is refused.
pub struct MessageRate {
    per_second: f64,
    tokens: f64,
    refilled: Instant,
}

impl MessageRate {
    pub fn new(per_second: u32) -> Self {
        let per_second = f64::from(per_second);
        Self { per_second, tokens: per_second, refilled: Instant::now() }
    }

    /// Takes one message's token; false when the bucket is empty.
    pub fn allow(&mut self) -> bool {
        let now = Instant::now();
        let elapsed = now.duration_since(self.refilled).as_secs_f64();
        self.tokens = (self.tokens + elapsed * self.per_second).min(self.per_second);
        self.refilled = now;
        if self.tokens < 1.0 {
            return false;
        }
        self.tokens -= 1.0;
        true
    }
}

/// The bytes the server holds at once for uploads on their way in (`max-upload-memory-bytes`): an update is
/// reserved its announced size when its header arrives, a rollout video its length before its body is read; the
/// reservation ends with the upload. Cheap to clone.
#[derive(Clone)]
pub struct UploadBudget {
    limit: u64,
    held: Arc<AtomicU64>,
}

/// Bytes reserved in an [`UploadBudget`], given back when dropped.
#[derive(Debug)]
pub struct Reservation {
    bytes: u64,
    held: Arc<AtomicU64>,
}

impl UploadBudget {
    pub fn new(limit: u64) -> Self {
        Self { limit, held: Arc::default() }
    }

    pub fn limit(&self) -> u64 {
        self.limit
    }

    /// Reserves `bytes`, or `None` when that would take the uploads in flight past the limit.
    pub fn reserve(&self, bytes: u64) -> Option<Reservation> {
        self.held
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |held| {
                held.checked_add(bytes).filter(|total| *total <= self.limit)
            })
            .ok()
            .map(|_| Reservation { bytes, held: Arc::clone(&self.held) })
    }

    /// Bytes reserved now.
    pub fn held(&self) -> u64 {
        self.held.load(Ordering::Acquire)
    }
}

impl Drop for Reservation {
    fn drop(&mut self) {
        self.held.fetch_sub(self.bytes, Ordering::AcqRel);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test(start_paused = true)]
    async fn joins_are_counted_per_address_and_minute() {
        let limiter = JoinLimiter::new(2);
        let (a, b): (IpAddr, IpAddr) = ("127.0.0.1".parse().unwrap(), "127.0.0.2".parse().unwrap());
        assert!(limiter.allow(a) && limiter.allow(a));
        assert!(!limiter.allow(a), "a third join in the minute");
        assert!(limiter.allow(b), "another address has its own count");
        tokio::time::advance(JOIN_WINDOW).await;
        assert!(limiter.allow(a), "a new minute");
    }

    #[tokio::test(start_paused = true)]
    async fn a_burst_of_one_seconds_messages_passes_and_a_flood_does_not() {
        let mut rate = MessageRate::new(10);
        assert!((0..10).all(|_| rate.allow()));
        assert!(!rate.allow());
        tokio::time::advance(Duration::from_millis(200)).await;
        assert!(rate.allow() && rate.allow(), "two tokens back after 0.2 s");
        assert!(!rate.allow());
    }

    #[test]
    fn reservations_fit_the_budget_and_end_when_dropped() {
        let budget = UploadBudget::new(100);
        let first = budget.reserve(60).unwrap();
        assert!(budget.reserve(41).is_none());
        let second = budget.reserve(40).unwrap();
        assert_eq!(budget.held(), 100);
        drop(first);
        assert_eq!(budget.held(), 40);
        assert!(budget.reserve(u64::MAX).is_none(), "no overflow");
        drop(second);
        assert_eq!(budget.held(), 0);
    }
}
