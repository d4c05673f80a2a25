//! The server's norm screen, before any strategy: an update whose change from the global model has a norm over
//! `update-norm-factor` times the reference, the median of the norms of this round's updates and of the previous
//! round's accepted ones (which a minority of volunteers scaling their changes up cannot move), is left out.
//!
//! The reference is known only once the round's last update is in, but updates are folded as they arrive, so the
//! screen decides each one as soon as the norms known bound it: with `r` sampled clients yet to send, the median
//! lies between the one where all `r` send a norm of zero and the one where all send an infinite norm (or none
//! sends). An update within the factor of the lower bound is kept in every outcome and folded at once; one beyond
//! the factor of the upper bound is left out in every outcome; only one between the two waits, held, until more
//! norms narrow the bounds or the round closes. The decision is exactly the rule's at the close, so it does not
//! depend on the order of arrival. With the previous round's norms at hand, honest updates (whose norms differ by
//! far less than the factor) are decided on arrival; in a run's first round, with no history, the first half of
//! the round's updates wait for the median.

/// What the screen says of one update.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Verdict {
    Keep,
    Outlier,
    /// Kept or left out depending on norms still to come.
    Undecided,
}

/// The norm screen's memory: the previous aggregated round's accepted norms. The factor is the run
/// configuration's, which the operator may change between rounds.
pub(super) struct NormScreen {
    previous: Vec<f64>,
}

impl NormScreen {
    pub(super) fn new(previous: Vec<f64>) -> Self {
        Self { previous }
    }

    /// The previous round's accepted norms become these.
    pub(super) fn remember(&mut self, accepted: Vec<f64>) {
        self.previous = accepted;
    }

    /// The previous norms and `known`, sorted.
    fn seen(&self, known: &[f64]) -> Vec<f64> {
        let mut seen: Vec<f64> = known.iter().chain(&self.previous).copied().collect();
        seen.sort_by(f64::total_cmp);
        seen
    }

    /// The reference once the round's norms are all `known`: the median of them and the previous round's.
    pub(super) fn reference(&self, known: &[f64]) -> f64 {
        let seen = self.seen(known);
        seen.get(seen.len() / 2).copied().unwrap_or(0.0)
    }

    /// The verdict at `factor` (0: off) on `norm`, one of the round's `known` norms, while `pending` sampled
    /// clients may still send one.
    pub(super) fn verdict(&self, factor: f64, norm: f64, known: &[f64], pending: usize) -> Verdict {
        if factor == 0.0 {
            return Verdict::Keep;
        }
        let seen = self.seen(known);
        let n = seen.len();
        // `r` more norms of zero shift the median's index by `r / 2` and the known ones up by `r`; `r` infinite
        // ones leave the known ones where they are.
        let lowest =
            (0..=pending).map(|r| ((n + r) / 2).checked_sub(r).map_or(0.0, |i| seen[i])).fold(f64::INFINITY, f64::min);
        let highest =
            (0..=pending).map(|r| seen.get((n + r) / 2).copied().unwrap_or(f64::INFINITY)).fold(0.0, f64::max);
        if norm <= factor * lowest {
            Verdict::Keep
        } else if norm > factor * highest {
            Verdict::Outlier
        } else {
            Verdict::Undecided
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_verdict_agrees_with_the_rule_at_the_close() {
        // Seeded rounds of honest norms around 1 and a few scaled by 30, arriving in every prefix of their order:
        // whatever the screen decides early is what the median of the complete round decides.
        let mut state = 11u64;
        let mut next = move || {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut decided_early = 0;
        for trial in 0..200 {
            let previous: Vec<f64> = (0..trial % 4).map(|_| 0.5 + next()).collect();
            let norms: Vec<f64> =
                (0..1 + trial % 9).map(|_| (0.5 + next()) * if next() < 0.2 { 30.0 } else { 1.0 }).collect();
            let screen = NormScreen::new(previous);
            let reference = screen.reference(&norms);
            for arrived in 1..=norms.len() {
                let known = &norms[..arrived];
                for &norm in known {
                    let at_close = if norm <= 10.0 * reference { Verdict::Keep } else { Verdict::Outlier };
                    match screen.verdict(10.0, norm, known, norms.len() - arrived) {
                        Verdict::Undecided => {}
                        early => {
                            assert_eq!(early, at_close, "trial {trial}, {arrived} arrived, norm {norm}");
                            decided_early += 1;
                        }
                    }
                }
                if arrived == norms.len() {
                    assert!(known.iter().all(|&n| screen.verdict(10.0, n, known, 0) != Verdict::Undecided));
                }
            }
        }
        assert!(decided_early > 0);
    }

    #[test]
    fn with_a_history_honest_updates_are_decided_on_arrival() {
        let screen = NormScreen::new(vec![1.0, 1.2, 0.9]);
        assert_eq!(screen.verdict(10.0, 1.1, &[1.1], 2), Verdict::Keep);
        // The median is 1.1 or 1.2 whatever the last client sends: 11.5 waits, 100 is out already.
        assert_eq!(screen.verdict(10.0, 11.5, &[1.1, 11.5], 1), Verdict::Undecided);
        assert_eq!(screen.verdict(10.0, 100.0, &[1.1, 100.0], 1), Verdict::Outlier);
        assert_eq!(screen.verdict(10.0, 11.5, &[1.1, 11.5, 1.0], 0), Verdict::Outlier);
        // Without one, the first of three waits for the median.
        let first = NormScreen::new(Vec::new());
        assert_eq!(first.verdict(10.0, 1.0, &[1.0], 2), Verdict::Undecided);
        assert_eq!(first.verdict(0.0, 1e9, &[1e9], 2), Verdict::Keep, "factor 0: the screen is off");
    }
}
