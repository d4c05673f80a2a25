//! `fedvla loadtest` with 100 volunteers: every update is accepted or refused with a reason, none is lost, every
//! volunteer finishes, and the report says which per-address bound it raised. No timing is asserted.

use std::time::Duration;

use fedvla_server::loadtest::{self, LoadOptions};

#[test]
fn a_hundred_volunteers_lose_no_update() {
    let base = tempfile::tempdir().unwrap();
    let options = LoadOptions {
        clients: 100,
        rounds: 2,
        local_steps: 5,
        time_limit: Duration::from_secs(300),
        output_dir: base.path().to_owned(),
    };
    let report = loadtest::run(&options).unwrap();
    assert!(!report.timed_out && report.client_failures.is_empty(), "{report}");
    assert_eq!((report.joined, report.completed_rounds), (100, 2), "{report}");
    let u = &report.updates;
    assert_eq!(u.sent, 200, "every volunteer sent an update each round: {report}");
    assert_eq!(u.lost, 0, "{report}");
    assert_eq!(u.accepted + u.refused.values().sum::<u64>(), u.sent, "{report}");
    assert_eq!((report.task_dispatch_ms.count, report.update_ack_ms.count), (200, 200), "{report}");
    assert_eq!(report.raised, ["joins-per-address-per-minute=100"], "{report}");
    // The report is what crosses to other processes (`--json`): it reads back as written.
    let json = serde_json::to_string(&report).unwrap();
    assert_eq!(serde_json::from_str::<loadtest::LoadReport>(&json).unwrap(), report);
    println!("{report}");
}
