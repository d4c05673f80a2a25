//! The operator console's server side: its live state ([`hub`]), the events it sends ([`events`]), the run
//! directory's rollouts as it shows them ([`gallery`]) and its HTTP API ([`api`]), every route of which wants the
//! operator token.

pub mod api;
mod events;
mod gallery;
mod hub;

pub use events::{AttemptOutcome, ClientRow, ConsoleEvent, RoundAttempt};
pub use hub::{ConsoleHub, LiveSnapshot, RunSummary};
