//! The benchmark harness in the normal build: broker, simulator and daemon as processes, one
//! toggled event input matched with its publication. Asserts values, never timings.

use std::time::Duration;

use rtu2mqtt::bench::harness::{wait_until, Harness, HarnessOptions};
use rtu2mqtt::bench::layout::BenchLayout;
use rtu2mqtt::bench::matching::match_changes;
use serde_json::json;

const PATIENCE: Duration = Duration::from_secs(30);
const EVERY: Duration = Duration::from_millis(20);

/// `with_library`: a controller's template library on the daemon's search path too.
fn run_one_change(baud: u32, with_library: bool) {
    let layout = BenchLayout {
        devices: 2,
        events: 2,
        registers: 3,
        baud,
        fast_devices: true,
    };
    let options = HarnessOptions::new(
        env!("CARGO_BIN_EXE_rtu2mqtt"),
        layout.bus(),
        vec![layout.template()],
    );
    let mut harness = Harness::start(&options).expect("harness starts");
    if with_library {
        harness.add_template_library().expect("library written");
    }
    let config = harness.daemon_config(layout.ports(harness.pty(), &json!({})), json!({}));
    harness.start_daemon(&config).expect("daemon starts");

    let topics = layout.value_topics();
    let all_published = wait_until(PATIENCE, EVERY, || {
        harness
            .with_publications(|seen| {
                topics
                    .iter()
                    .all(|topic| seen.iter().any(|p| &p.topic == topic))
            })
            .then_some(())
    });
    assert!(
        all_published.is_some(),
        "not every value was published at {baud}:\n{}",
        harness.daemon_log()
    );
    let since = rtu2mqtt::bench::harness::monotonic_ns();
    harness
        .control(&json!({"cmd": "set", "device": 2, "type": "input", "address": 1, "value": 4321}))
        .unwrap();
    let reply = harness
        .control(&json!({"cmd": "toggle", "device": 2, "type": "discrete", "address": 1}))
        .unwrap();
    assert_eq!(reply["value"], 1);

    let topic_of = |c: &rtu2mqtt::bench::harness::Change| {
        layout.topic_of(c.address, &c.register_type, c.register, c.value)
    };
    let report = wait_until(PATIENCE, EVERY, || {
        let changes: Vec<_> = harness
            .changes()
            .into_iter()
            .filter(|c| c.origin == "control")
            .collect();
        let report = match_changes(&changes, &harness.publications(), since, topic_of);
        (report.matched == 2).then_some(report)
    })
    .unwrap_or_else(|| {
        panic!(
            "both changes published at {baud}:\n{}",
            harness.daemon_log()
        )
    });
    assert_eq!(report.changes, 2);
    assert_eq!((report.lost, report.wrong, report.duplicates), (0, 0, 0));
    assert_eq!(report.latencies_ns.len(), 2);
    let published = harness.with_publications(|seen| {
        seen.iter()
            .rev()
            .find(|p| p.topic == "/devices/bench_2/controls/R1")
            .map(|p| p.payload.clone())
    });
    assert_eq!(published.as_deref(), Some("4321"));

    let stats = harness.bus_stats().unwrap();
    assert!(stats["requests"].as_u64().unwrap() > 0, "{stats}");
    assert!(stats["registers_read"].as_u64().unwrap() >= 3, "{stats}");
    let daemon = harness.daemon_stats().expect("daemon running");
    assert!(daemon.peak_rss_kib > 0);
    harness.stop_daemon();
    assert!(harness.daemon_stats().is_none());
}

#[test]
fn harness_matches_a_change_with_its_publication_at_115200() {
    run_one_change(115_200, false);
}

#[test]
fn harness_matches_a_change_with_its_publication_at_9600() {
    run_one_change(9600, false);
}

/// As scenario 7 measures memory with it: the bench's own templates still win.
#[test]
fn harness_with_a_template_library_on_the_search_path() {
    run_one_change(115_200, true);
}
