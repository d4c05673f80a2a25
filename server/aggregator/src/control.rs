//! The operator's hold on a run ([`Controls`]): whether rounds may run (start, pause, resume, stop) and settings
//! the next round takes up. The console changes them; the coordinator reads them at round boundaries only.

use std::sync::{Arc, Mutex, MutexGuard};

use serde::{Deserialize, Serialize};
use serde_json::json;
use tokio::sync::watch;

use crate::config::{ConfigError, RunConfig};

/// What the operator may change while the run goes on. Each applies from the next round's tasks on; a field left
/// out (`None`) is not changed.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case", deny_unknown_fields)]
pub struct Settings {
    #[serde(skip_serializing_if = "Option::is_none")]
    pub local_steps: Option<u32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub batch_size: Option<u32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lr: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fraction_fit: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rollout_episodes: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub client_rollout_episodes: Option<u32>,
}

impl Settings {
    /// Every setting as `config` has it.
    pub fn of(config: &RunConfig) -> Self {
        Self {
            local_steps: Some(config.local_steps),
            batch_size: Some(config.batch_size),
            lr: Some(config.lr),
            fraction_fit: Some(config.fraction_fit),
            rollout_episodes: Some(config.rollout_episodes),
            client_rollout_episodes: Some(config.client_rollout_episodes),
        }
    }

    pub fn is_empty(&self) -> bool {
        *self == Self::default()
    }

    /// `config` with these settings applied, validated as a whole.
    pub fn applied_to(&self, config: &RunConfig) -> Result<RunConfig, ConfigError> {
        let mut out = config.clone();
        out.local_steps = self.local_steps.unwrap_or(out.local_steps);
        out.batch_size = self.batch_size.unwrap_or(out.batch_size);
        out.lr = self.lr.unwrap_or(out.lr);
        out.fraction_fit = self.fraction_fit.unwrap_or(out.fraction_fit);
        out.rollout_episodes = self.rollout_episodes.unwrap_or(out.rollout_episodes);
        out.client_rollout_episodes = self.client_rollout_episodes.unwrap_or(out.client_rollout_episodes);
        out.validate()?;
        Ok(out)
    }

    /// The settable keys, as the API spells them.
    pub fn keys() -> Vec<String> {
        let all = json!(Settings::of(&RunConfig::default()));
        all.as_object().expect("settings serialize to an object").keys().cloned().collect()
    }

    /// Adds a later change on top of this one: its settings win.
    pub fn merge(&mut self, later: Settings) {
        self.local_steps = later.local_steps.or(self.local_steps);
        self.batch_size = later.batch_size.or(self.batch_size);
        self.lr = later.lr.or(self.lr);
        self.fraction_fit = later.fraction_fit.or(self.fraction_fit);
        self.rollout_episodes = later.rollout_episodes.or(self.rollout_episodes);
        self.client_rollout_episodes = later.client_rollout_episodes.or(self.client_rollout_episodes);
    }
}

/// Whether rounds may start, as the operator decided.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum RunState {
    /// `auto-start = false` and the operator has not pressed Start yet.
    WaitingForStart,
    Running,
    /// The current round finishes; no new one starts.
    Paused,
    /// The current round finishes, then the run ends.
    Stopping,
    Finished,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ControlAction {
    Start,
    Pause,
    Resume,
    Stop,
}

impl ControlAction {
    fn name(self) -> &'static str {
        match self {
            Self::Start => "start",
            Self::Pause => "pause",
            Self::Resume => "resume",
            Self::Stop => "stop",
        }
    }
}

impl RunState {
    /// The state `action` leads to, or why it cannot be taken now. Start and Resume both let rounds run.
    pub fn after(self, action: ControlAction) -> Result<RunState, String> {
        use ControlAction::{Pause, Resume, Start, Stop};
        match (self, action) {
            (Self::Finished, _) => Err(format!("the run is finished; there is nothing to {}", action.name())),
            (Self::Stopping, Stop) => Ok(Self::Stopping),
            (Self::Stopping, _) => {
                Err(format!("the run is stopping after the current round; it cannot {}", action.name()))
            }
            (_, Stop) => Ok(Self::Stopping),
            (_, Start | Resume) => Ok(Self::Running),
            (_, Pause) => Ok(Self::Paused),
        }
    }
}

/// Shared by the coordinator and whoever operates the run; cheap to clone.
#[derive(Clone)]
pub struct Controls(Arc<ControlState>);

struct ControlState {
    run_state: watch::Sender<RunState>,
    live: Mutex<Pending>,
}

struct Pending {
    /// The configuration the next round runs with: the run's, with the operator's settings applied.
    config: RunConfig,
    /// Settings changed since a round last took them up.
    changed: Settings,
}

impl Controls {
    /// Controls of a run configured by `config`: running at once, or waiting for Start without `auto-start`.
    pub fn new(config: &RunConfig) -> Self {
        let initial = if config.auto_start { RunState::Running } else { RunState::WaitingForStart };
        Self(Arc::new(ControlState {
            run_state: watch::channel(initial).0,
            live: Mutex::new(Pending { config: config.clone(), changed: Settings::default() }),
        }))
    }

    /// The operator's run state, for the coordinator to wait on.
    pub fn run_state(&self) -> watch::Receiver<RunState> {
        self.0.run_state.subscribe()
    }

    pub fn state(&self) -> RunState {
        *self.0.run_state.borrow()
    }

    /// Applies the operator's `action`; the coordinator sees the new state at its next round boundary.
    pub fn control(&self, action: ControlAction) -> Result<RunState, String> {
        let mut outcome = Err(String::new());
        self.0.run_state.send_if_modified(|state| {
            outcome = state.after(action);
            match outcome {
                Ok(next) if next != *state => {
                    *state = next;
                    true
                }
                _ => false,
            }
        });
        let state = outcome?;
        tracing::info!(?action, ?state, "operator control");
        Ok(state)
    }

    /// Marks the run over (the coordinator's last act).
    pub fn finish(&self) {
        self.0.run_state.send_replace(RunState::Finished);
    }

    /// Validates the operator's `change` against the run's configuration and queues it for the next round.
    /// Returns every setting as the next round will have it.
    pub fn change_settings(&self, change: Settings) -> Result<Settings, ConfigError> {
        let mut live = self.live();
        live.config = change.applied_to(&live.config)?;
        tracing::info!(changed = %json!(change), "operator changed settings; they apply from the next round's tasks on");
        live.changed.merge(change);
        Ok(Settings::of(&live.config))
    }

    /// The configuration with every pending change applied, and those changes; `None` when there are none.
    pub fn take_settings(&self) -> Option<(RunConfig, Settings)> {
        let mut live = self.live();
        let changed = std::mem::take(&mut live.changed);
        (!changed.is_empty()).then(|| (live.config.clone(), changed))
    }

    /// The configuration the next round runs with, and the settings changed since a round last took them up.
    pub fn next_round(&self) -> (RunConfig, Settings) {
        let live = self.live();
        (live.config.clone(), live.changed.clone())
    }

    fn live(&self) -> MutexGuard<'_, Pending> {
        self.0.live.lock().expect("controls lock")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn run_state_transitions() {
        use ControlAction::*;
        use RunState::*;
        assert_eq!(WaitingForStart.after(Start), Ok(Running));
        assert_eq!(Running.after(Pause), Ok(Paused));
        assert_eq!(Paused.after(Resume), Ok(Running));
        assert_eq!(Paused.after(Stop), Ok(Stopping));
        assert_eq!(Running.after(Resume), Ok(Running), "idempotent");
        assert_eq!(Stopping.after(Stop), Ok(Stopping));
        assert_eq!(
            Stopping.after(Resume).unwrap_err(),
            "the run is stopping after the current round; it cannot resume"
        );
        assert_eq!(Finished.after(Pause).unwrap_err(), "the run is finished; there is nothing to pause");
    }

    #[test]
    fn settings_apply_validate_and_merge() {
        let config = RunConfig::default();
        let mut change = Settings { local_steps: Some(7), ..Settings::default() };
        assert_eq!(change.applied_to(&config).unwrap().local_steps, 7);
        let err = Settings { fraction_fit: Some(1.5), ..Settings::default() }.applied_to(&config).unwrap_err();
        assert_eq!(err.to_string(), "invalid configuration: fraction-fit must be in (0, 1], got 1.5");
        change.merge(Settings { lr: Some(0.1), local_steps: Some(9), ..Settings::default() });
        assert_eq!(change, Settings { local_steps: Some(9), lr: Some(0.1), ..Settings::default() });
        let err = serde_json::from_str::<Settings>(r#"{"local_steps": 3}"#).unwrap_err().to_string();
        assert!(err.contains("unknown field `local_steps`") && err.contains("`local-steps`"), "{err}");
        let mut keys = Settings::keys();
        keys.sort();
        assert_eq!(
            keys,
            ["batch-size", "client-rollout-episodes", "fraction-fit", "local-steps", "lr", "rollout-episodes"]
        );
    }
}
