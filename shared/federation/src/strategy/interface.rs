//! The aggregation interface every strategy implements, and [`aggregate`], a whole round folded at once.

use super::dp::PrivacyReport;
use crate::error::AggregateError;
use crate::protocol::StrategyParams;
use crate::tensors::NamedTensors;

/// One client's part in a round: its trained tensors, the weight the server gives it (the examples of the shard
/// it assigned), what the strategies that need more know of it, where the server knows it.
#[derive(Debug, Clone, Copy)]
pub struct Contribution<'a> {
    pub tensors: &'a NamedTensors,
    pub examples: u64,
    /// The mean loss of its local training, as the client reported it (QFedAvg weighs by it).
    pub train_loss: Option<f64>,
    /// Who trained it, the same from round to round (its shard): SCAFFOLD keeps a control variate per client.
    pub client: Option<u64>,
    /// The sum of the learning rates of the round's local steps (SCAFFOLD's option II divides by it).
    pub lr_sum: Option<f64>,
}

impl<'a> Contribution<'a> {
    /// The same client's part with other tensors (a wrapper's clipped copy).
    pub fn with_tensors(self, tensors: &'a NamedTensors) -> Self {
        Self { tensors, ..self }
    }
}

/// Tensors and weight, no reported loss.
impl<'a> From<(&'a NamedTensors, u64)> for Contribution<'a> {
    fn from((tensors, examples): (&'a NamedTensors, u64)) -> Self {
        Self { tensors, examples, train_loss: None, client: None, lr_sum: None }
    }
}

/// One round's aggregation in progress.
pub trait Aggregation: Send {
    /// Folds one client's update.
    fn fold(&mut self, update: Contribution<'_>) -> Result<(), AggregateError>;

    /// The round's aggregate of everything folded.
    fn finish(self: Box<Self>) -> Result<NamedTensors, AggregateError>;
}

/// The next global model, with the strategy state it leaves once committed.
#[derive(Debug, Clone, PartialEq)]
pub struct Step {
    pub global: NamedTensors,
    pub state: NamedTensors,
}

/// Turns the clients' updates of each round into the next global model.
pub trait Strategy: Send {
    /// Parameters clients need for local training, sent in every task.
    fn client_params(&self) -> StrategyParams;

    /// Opens a round whose clients trained from `global`.
    fn begin(&self, global: &NamedTensors) -> Box<dyn Aggregation>;

    /// The next global model from `global` and the round's `aggregate`; nothing of `self` changes until
    /// [`Strategy::commit`].
    fn step(&self, global: &NamedTensors, aggregate: NamedTensors) -> Result<Step, AggregateError> {
        let _ = global;
        Ok(Step { global: aggregate, state: NamedTensors::new() })
    }

    /// Takes up the state of a committed round.
    fn commit(&mut self, state: NamedTensors) {
        let _ = state;
    }

    /// The state to save with a round (and to hand back to [`Strategy::commit`] on resume).
    fn state(&self) -> NamedTensors {
        NamedTensors::new()
    }

    /// The differential privacy the committed rounds have spent, for a strategy that adds noise.
    fn privacy(&self) -> Option<PrivacyReport> {
        None
    }

    /// What client `client` adds to the direction of each of its local steps next round, for a strategy whose
    /// [`StrategyParams::control_variates`] is set (empty: nothing yet).
    fn client_correction(&self, client: u64) -> Option<NamedTensors> {
        let _ = client;
        None
    }
}

/// Every update of a round folded in the order given: the aggregate of `strategy` over `updates` from `global`, and the
/// step it leads to (uncommitted).
pub fn aggregate<'a>(
    strategy: &dyn Strategy,
    global: &NamedTensors,
    updates: impl IntoIterator<Item = impl Into<Contribution<'a>>>,
) -> Result<Step, AggregateError> {
    let mut round = strategy.begin(global);
    for (index, update) in updates.into_iter().enumerate() {
        round.fold(update.into()).map_err(|e| match e {
            AggregateError::Mismatch { source, .. } => AggregateError::Mismatch { index, source },
            AggregateError::Loss { rule, loss, .. } => AggregateError::Loss { index, rule, loss },
            AggregateError::Unknown { rule, what, .. } => AggregateError::Unknown { index, rule, what },
            AggregateError::OutOfRange { value, limit, .. } => AggregateError::OutOfRange { index, value, limit },
            other => other,
        })?;
    }
    conclude(strategy, global, round)
}

/// Closes a round whose updates `round` folded (as they arrived): its aggregate, and the step it leads to from
/// `global` (uncommitted), checked finite.
pub fn conclude(
    strategy: &dyn Strategy,
    global: &NamedTensors,
    round: Box<dyn Aggregation>,
) -> Result<Step, AggregateError> {
    let step = strategy.step(global, round.finish()?)?;
    // Finite inputs average to finite values; the check keeps that promise for every strategy's output.
    step.global.validate(&global.spec()).map_err(AggregateError::Aggregate)?;
    Ok(step)
}

/// A one-tensor model `w = v`, for the strategies' tests.
#[cfg(test)]
pub(super) fn one(v: [f32; 2]) -> NamedTensors {
    let mut t = NamedTensors::new();
    t.insert("w", vec![2], v.to_vec()).unwrap();
    t
}
