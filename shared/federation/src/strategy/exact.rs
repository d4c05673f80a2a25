//! Exact, order-independent sums of weighted values, what every streaming rule accumulates a round in. A value is
//! put on a fixed-point grid of `2^-FRACTION_BITS` (a function of the value alone) and its weighted integer added
//! to the value's slot; integer addition is associative, so the sum, and the aggregate made of it, are the same
//! bits whatever order the updates arrive in (an `f64` running sum is not: `(a + b) + c` rounds differently from
//! `a + (b + c)`), and a run is reproducible from its seed.
//!
//! A slot's sum is an `i128`, kept as two words: its `i64` part, one per value of the model, and the multiples of
//! `2^64` beyond it, which only a slot whose sum has left the `i64` range has (it takes a sum of weight x value
//! beyond `2^17`, e.g. a value of 5 over 30,000 examples): those are kept by slot while few, for every slot once
//! many. Memory: 8 bytes per value of the model whatever the number of updates, 16 at most, from the first update
//! added on (a round's sum takes no memory while its clients train).
//!
//! The grid keeps every f32 of magnitude at least `2^-23` exactly and rounds smaller ones by at most `2^-47`; a value
//! of magnitude `MAX_MAGNITUDE` or more (no model's, an attacker's) is refused, which keeps each weighted term
//! below `2^126`. The sum of the terms' magnitudes is kept beside the slots: below `2^127` no slot can have
//! overflowed, in any order; at or beyond it (weights near `u64::MAX`) the round is refused as a whole.

use std::collections::HashMap;

use crate::error::AggregateError;

const FRACTION_BITS: i32 = 46;
/// `2^16`: values at or beyond it are refused.
pub(super) const MAX_MAGNITUDE: f64 = 65_536.0;
const SCALE: f64 = (1u64 << FRACTION_BITS) as f64;

/// The running sum of weighted values, one slot per value of the model (tensors laid end to end).
#[derive(Debug, Clone)]
pub(super) struct ExactSum {
    /// Each slot's sum modulo `2^64`, as a signed word; empty (every slot 0) before the first value is added.
    low: Vec<i64>,
    /// The multiples of `2^64` the slots' sums hold beyond `low`.
    high: High,
    len: usize,
    /// `sum of weight * max |grid value|` over the terms added: while below `2^127`, no slot has overflowed.
    bound: u128,
}

/// The high words of the slots' sums: by slot while at most one slot in [`SPARSE_SHARE`] has one, for every slot
/// beyond.
#[derive(Debug, Clone)]
enum High {
    Sparse(HashMap<usize, i64>),
    Dense(Vec<i64>),
}

/// Past one slot in this many holding a high word, every slot gets one (8 bytes, against the map's ~20 each).
const SPARSE_SHARE: usize = 8;

impl High {
    /// Every one of the `len` slots' high words, in slot order: the map's few walked in order beside the slots,
    /// not looked up once per slot.
    fn words(&self, len: usize) -> Box<dyn Iterator<Item = i64> + '_> {
        match self {
            Self::Dense(words) => Box::new(words.iter().copied()),
            Self::Sparse(map) => {
                let mut held: Vec<(usize, i64)> = map.iter().map(|(&slot, &word)| (slot, word)).collect();
                held.sort_unstable();
                let mut held = held.into_iter().peekable();
                Box::new((0..len).map(move |slot| held.next_if(|&(s, _)| s == slot).map_or(0, |(_, word)| word)))
            }
        }
    }

    fn add(&mut self, slot: usize, carry: i64, len: usize) {
        match self {
            Self::Sparse(map) => {
                let word = map.entry(slot).or_insert(0);
                *word = word.wrapping_add(carry);
                if map.len() > len / SPARSE_SHARE {
                    let mut words = vec![0; len];
                    for (&slot, &word) in map.iter() {
                        words[slot] = word;
                    }
                    *self = Self::Dense(words);
                }
            }
            Self::Dense(words) => words[slot] = words[slot].wrapping_add(carry),
        }
    }
}

impl ExactSum {
    pub(super) fn zeros(len: usize) -> Self {
        Self { low: Vec::new(), high: High::Sparse(HashMap::new()), len, bound: 0 }
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
        if self.low.is_empty() {
            self.low = vec![0; self.len];
        }
        let w = i128::from(weight);
        for ((slot, low), v) in self.low.iter_mut().enumerate().skip(offset).zip(values()) {
            // The term is `high * 2^64 + low_term`, `low_term` its low word read as signed.
            let term = w * i128::from(grid(v));
            let low_term = term as i64;
            let mut carry = ((term - i128::from(low_term)) >> 64) as i64;
            let (sum, wrapped) = low.overflowing_add(low_term);
            *low = sum;
            if wrapped {
                carry += if low_term > 0 { 1 } else { -1 };
            }
            if carry != 0 {
                self.high.add(slot, carry, self.len);
            }
        }
        self.bound = self.bound.saturating_add(u128::from(weight) * u128::from(largest));
        Ok(())
    }

    /// Each slot's sum divided by `divisor`, or [`AggregateError::Overflow`] when a sum may have overflowed.
    pub(super) fn divided_by(&self, divisor: f64) -> Result<impl Iterator<Item = f64> + '_, AggregateError> {
        if self.bound >= 1 << 127 {
            return Err(AggregateError::Overflow);
        }
        let unset = if self.low.is_empty() { self.len } else { 0 };
        let sums = self
            .low
            .iter()
            .zip(self.high.words(self.len))
            .map(|(&low, high)| (i128::from(high) << 64) + i128::from(low))
            .chain(std::iter::repeat_n(0, unset));
        Ok(sums.map(move |s| s as f64 / SCALE / divisor))
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

    /// Sums beyond the `i64` range, reached in every order and back, are the `i128` sums, whether a few slots
    /// carry a high word or every slot does.
    #[test]
    fn sums_beyond_i64_are_exact_in_every_order() {
        let reference = |terms: &[(u64, f64)]| -> f64 {
            let sum: i128 = terms.iter().map(|&(w, v)| i128::from(w) * i128::from(grid(v))).sum();
            sum as f64 / SCALE / 7.0
        };
        // Slot 0 climbs past 2^63 and comes back; slot 1 goes below -2^63; slot 2 stays small.
        let updates: [(u64, [f64; 3]); 4] = [
            (1 << 20, [3.0, -3.0, 0.5]),
            (1 << 20, [2.5, -1.0, -0.25]),
            (3, [-1.5, -1.75, 1e-6]),
            (1 << 21, [-2.0, 0.75, 0.125]),
        ];
        for dense in [false, true] {
            let mut sums = Vec::new();
            for order in [[0, 1, 2, 3], [3, 2, 1, 0], [1, 3, 0, 2]] {
                let mut sum = ExactSum::zeros(3);
                if dense {
                    sum.high = High::Dense(vec![0; 3]);
                }
                for i in order {
                    let (w, values) = updates[i];
                    sum.add(0, w, || values.into_iter()).unwrap();
                }
                sums.push(sum.divided_by(7.0).unwrap().map(f64::to_bits).collect::<Vec<_>>());
            }
            assert!(sums.iter().all(|s| *s == sums[0]));
            for slot in 0..3 {
                let terms: Vec<(u64, f64)> = updates.iter().map(|&(w, v)| (w, v[slot])).collect();
                assert_eq!(f64::from_bits(sums[0][slot]), reference(&terms), "slot {slot}");
            }
        }
        // A few slots with a high word among many (5 and 40; the others' sums stay within i64): kept by slot, each
        // read back at its own slot.
        let small = 2f64.powi(-10);
        let value = |slot: usize| match slot {
            5 => 7.0,
            40 => -7.0,
            _ => small,
        };
        let mut sum = ExactSum::zeros(64);
        for _ in 0..2 {
            sum.add(0, 1 << 20, || (0..64).map(value)).unwrap();
        }
        assert!(matches!(&sum.high, High::Sparse(map) if map.len() == 2));
        let means: Vec<f64> = sum.divided_by(7.0).unwrap().collect();
        let twice = |v: f64| reference(&[(1 << 20, v), (1 << 20, v)]);
        assert_eq!((means[5], means[40], means[6], means[63]), (twice(7.0), twice(-7.0), twice(small), twice(small)));
        // Many slots with a high word: the map gives way to a word for every slot, and the sums stay exact.
        let mut sum = ExactSum::zeros(16);
        sum.add(0, 1 << 20, || [7.0; 16].into_iter()).unwrap();
        sum.add(0, 1 << 20, || [7.0; 16].into_iter()).unwrap();
        assert!(matches!(sum.high, High::Dense(_)));
        let expected = reference(&[(1 << 20, 7.0), (1 << 20, 7.0)]) * 7.0;
        assert!(sum.divided_by(1.0).unwrap().all(|s| s == expected));
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
