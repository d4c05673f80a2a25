//! The bounds on what strangers' input may cost the server beyond the listener's ([`crate::http`]): joins per
//! address per minute ([`JoinLimiter`]) and messages per second on one connection ([`MessageRate`]); the memory
//! held at once for uploads on their way in is the aggregator's [`fedvla_aggregator::upload_budget`], since an
//! update's reservation lasts until the coordinator has taken it. Each is a run configuration key; what they refuse
//! is counted on the console.

use std::collections::HashMap;
use std::net::IpAddr;
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
}
