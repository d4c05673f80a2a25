//! The bytes the server holds at once for uploads on their way in (`max-upload-memory-bytes`), updates and rollout
//! videos together. An update is reserved its announced size when its header arrives, and the reservation travels
//! with the decoded update to the coordinator ([`crate::coordinator::UpdateReceived`]), ending once the round has
//! taken it (folded, or held for the norm screen): so updates a slow fold has not taken yet count, and a full
//! budget holds the next update's frames back in its socket ([`UploadBudget::reserve_when_free`]) instead of
//! letting decoded updates pile up in the coordinator's channel. A video is reserved its length before its body is
//! read, or refused at once when that does not fit (HTTP 503, try again).

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use tokio::sync::Notify;

/// The budget; cheap to clone.
#[derive(Clone)]
pub struct UploadBudget {
    limit: u64,
    held: Arc<Held>,
}

#[derive(Debug, Default)]
struct Held {
    bytes: AtomicU64,
    /// Woken whenever a reservation ends.
    freed: Notify,
}

/// Bytes reserved in an [`UploadBudget`], given back when dropped.
#[derive(Debug)]
pub struct Reservation {
    bytes: u64,
    held: Arc<Held>,
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
            .bytes
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |held| {
                held.checked_add(bytes).filter(|total| *total <= self.limit)
            })
            .ok()
            .map(|_| Reservation { bytes, held: Arc::clone(&self.held) })
    }

    /// Reserves `bytes` once the reservations before it leave room (waiting as long as they last: the caller bounds
    /// the wait); `None` at once when `bytes` exceed the whole budget.
    pub async fn reserve_when_free(&self, bytes: u64) -> Option<Reservation> {
        if bytes > self.limit {
            return None;
        }
        loop {
            // Registered before the attempt, so that a reservation ending between the two still wakes it.
            let freed = self.held.freed.notified();
            tokio::pin!(freed);
            freed.as_mut().enable();
            if let Some(reservation) = self.reserve(bytes) {
                return Some(reservation);
            }
            freed.await;
        }
    }

    /// Bytes reserved now.
    pub fn held(&self) -> u64 {
        self.held.bytes.load(Ordering::Acquire)
    }
}

impl Drop for Reservation {
    fn drop(&mut self) {
        self.held.bytes.fetch_sub(self.bytes, Ordering::AcqRel);
        self.held.freed.notify_waiters();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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

    #[tokio::test]
    async fn a_reservation_that_does_not_fit_waits_for_room_and_one_that_never_fits_is_refused() {
        let budget = UploadBudget::new(100);
        assert!(budget.reserve_when_free(101).await.is_none(), "more than the whole budget");
        let first = budget.reserve(70).unwrap();
        let waiting = tokio::spawn({
            let budget = budget.clone();
            async move { budget.reserve_when_free(50).await }
        });
        // However long it waits, it cannot reserve while the first holds 70 of 100.
        tokio::task::yield_now().await;
        assert_eq!(budget.held(), 70);
        drop(first);
        let second = waiting.await.unwrap().expect("room once the first ended");
        assert_eq!(budget.held(), 50);
        drop(second);
        assert_eq!(budget.held(), 0);
    }
}
