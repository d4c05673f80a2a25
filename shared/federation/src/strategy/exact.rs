//! Exact, order-independent sums of weighted values, what every streaming rule accumulates a round in. A value is
//! put on a fixed-point grid of `2^-FRACTION_BITS` (a function of the value alone) and its weighted integer added
//! to an `i128` per value; integer addition is associative, so the sum, and the aggregate made of it, are the same
//! bits whatever order the updates arrive in (an `f64` running sum is not: `(a + b) + c` rounds differently from
//! `a + (b + c)`), and a run is reproducible from its seed. Memory: 16 bytes per value of the model, whatever the
//! number of updates.
//!
//! The grid keeps every f32 of magnitude at least `2^-23` exactly and rounds smaller ones by at most `2^-47`; a value
//! of magnitude `MAX_MAGNITUDE` or more (no model's, an attacker's) is refused, which keeps each weighted term
//! below `2^126`. The sum of the terms' magnitudes is kept beside the slots: below `2^127` no slot can have
//! overflowed, in any order; at or beyond it (weights near `u64::MAX`) the round is refused as a whole.

use crate::error::AggregateError;

const FRACTION_BITS: i32 = 46;
/// `2^16`: values at or beyond it are refused.
pub(super) const MAX_MAGNITUDE: f64 = 65_536.0;
const SCALE: f64 = (1u64 << FRACTION_BITS) as f64;

/// The running sum of weighted values, one slot per value of the model (tensors laid end to end).
#[derive(Debug, Clone)]
pub(super) struct ExactSum {
    sums: Vec<i128>,
    /// `sum of weight * max |grid value|` over the terms added: while below `2^127`, no slot has overflowed.
    bound: u128,
}

impl ExactSum {
    pub(super) fn zeros(len: usize) -> Self {
        Self { sums: vec![0; len], bound: 0 }
    }

    /// Adds `weight * value` for each value `values()` yields, slot by slot from `offset`. Nothing is added when a
    /// value is out of range (`Err` with it), so a refused update leaves the sum as it was.
    pub(super) fn add<I: Iterator<Item = f64>>(
        &mut self,
        offset: usize,
        weight: u64,
        values: impl Fn() -> I,
    ) -> Result<(), f64> {
        in_range(values())?;
        let largest = values().map(|v| grid(v).unsigned_abs()).max().unwrap_or(0);
        let w = i128::from(weight);
        for (slot, v) in self.sums[offset..].iter_mut().zip(values()) {
            *slot = slot.wrapping_add(w * i128::from(grid(v)));
        }
        self.bound = self.bound.saturating_add(u128::from(weight) * u128::from(largest));
        Ok(())
    }

    /// Each slot's sum divided by `divisor`, or [`AggregateError::Overflow`] when a sum may have overflowed.
    pub(super) fn divided_by(&self, divisor: f64) -> Result<impl Iterator<Item = f64> + '_, AggregateError> {
        if self.bound >= 1 << 127 {
            return Err(AggregateError::Overflow);
        }
        Ok(self.sums.iter().map(move |&s| s as f64 / SCALE / divisor))
    }
}

/// Whether [`ExactSum::add`] takes every one of `values`: `Err` with the first it refuses.
pub(super) fn in_range(mut values: impl Iterator<Item = f64>) -> Result<(), f64> {
    match values.find(|v| v.is_nan() || v.abs() >= MAX_MAGNITUDE) {
        Some(v) => Err(v),
        None => Ok(()),
    }
}

/// `v` on the grid: `round(v * 2^FRACTION_BITS)`, exact for `|v| < MAX_MAGNITUDE` (below `2^62`).
fn grid(v: f64) -> i64 {
    (v * SCALE).round() as i64
}

/// Update `index`'s refusal for holding `value`.
pub(super) fn out_of_range(index: usize) -> impl Fn(f64) -> AggregateError {
    move |value| AggregateError::OutOfRange { index, value, limit: MAX_MAGNITUDE }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_sum_is_the_same_in_every_order_where_f64_is_not() {
        // 2^15 + 2^-40 needs 56 bits: an f64 running sum loses the small term in one order and keeps it in another.
        let terms = [2f64.powi(15), 2f64.powi(-40), -(2f64.powi(15))];
        let f64_sum = |order: [usize; 3]| order.iter().fold(0.0, |a, &i| a + terms[i]);
        assert_ne!(f64_sum([0, 1, 2]), f64_sum([0, 2, 1]));
        let exact = |order: [usize; 3]| {
            let mut sum = ExactSum::zeros(1);
            for i in order {
                sum.add(0, 3, || std::iter::once(terms[i])).unwrap();
            }
            sum.divided_by(3.0).unwrap().next().unwrap()
        };
        let orders = [[0, 1, 2], [0, 2, 1], [1, 0, 2], [1, 2, 0], [2, 0, 1], [2, 1, 0]];
        assert!(orders.iter().all(|&o| exact(o).to_bits() == exact([0, 1, 2]).to_bits()));
        assert_eq!(exact([0, 1, 2]), 2f64.powi(-40));
    }

    #[test]
    fn out_of_range_values_are_refused_and_leave_the_sum_alone() {
        let mut sum = ExactSum::zeros(2);
        sum.add(0, 1, || [1.0, 2.0].into_iter()).unwrap();
        assert_eq!(sum.add(0, 1, || [5.0, -MAX_MAGNITUDE].into_iter()), Err(-MAX_MAGNITUDE));
        assert_eq!(sum.add(0, 1, || [f64::NAN, 0.0].into_iter()).map_err(f64::is_nan), Err(true));
        assert_eq!(sum.divided_by(1.0).unwrap().collect::<Vec<_>>(), vec![1.0, 2.0]);
    }

    #[test]
    fn sums_that_could_overflow_are_refused() {
        // Four terms of about 2^126 in magnitude: refused, though these happen to cancel (the bound cannot know).
        let big = MAX_MAGNITUDE - 1.0;
        let mut sum = ExactSum::zeros(1);
        for v in [big, big, -big, -big] {
            sum.add(0, u64::MAX, || std::iter::once(v)).unwrap();
        }
        assert_eq!(sum.divided_by(1.0).map(|mut s| s.next()), Err(AggregateError::Overflow));
        let mut sum = ExactSum::zeros(1);
        for v in [big, -big] {
            sum.add(0, 1 << 40, || std::iter::once(v)).unwrap();
        }
        assert_eq!(sum.divided_by(1.0).unwrap().next(), Some(0.0));
    }
}
