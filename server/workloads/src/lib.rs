//! What a federation trains, and the sim around it: the [`workload::Workload`] interface and its two
//! implementations, SmolVLA on SO-100 episodes ([`smolvla`]) and a least-squares toy that exercises the
//! machinery in milliseconds ([`linreg`]); recording the sim's expert as LeRobot datasets ([`datagen`]); and
//! rolling policies out in the sim with videos and `results.json` ([`sim_eval`]); the burn device native
//! trainers step on ([`device`]).

pub mod datagen;
pub mod device;
pub mod linreg;
pub mod sim_eval;
pub mod smolvla;
pub mod workload;
