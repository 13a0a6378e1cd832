//! `rtu2mqtt bench` (feature `bench`): runs the benchmark scenarios against the simulator, a
//! real mosquitto and this binary's `run`, then writes `latest.md` and PNG plots (docs/bench.md).

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use anyhow::Context;

use crate::bench::bare_master::{run_bare_master, FloorMaster};
use crate::bench::plots;
use crate::bench::report::{markdown, Environment};
use crate::bench::scan::{devices_at_three_settings, run_scan};
use crate::bench::scenarios::{plan, run, BenchOptions, RunResult};

/// Run the benchmarks (event latency, cost, bus efficiency, …) and write a report with plots.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Where latest.md and the PNGs go.
    #[arg(long, value_name = "DIR", default_value = "bench/results")]
    pub out: PathBuf,
    /// Each scenario briefly (about a minute in all): to check the bench, not to quote numbers.
    #[arg(long)]
    pub quick: bool,
    /// Only these scenarios (e.g. `--only 2,7`).
    #[arg(long, value_delimiter = ',', value_name = "N,…")]
    pub only: Vec<u8>,
    /// Line speeds to run at (8N2).
    #[arg(
        long,
        value_delimiter = ',',
        value_name = "BAUD,…",
        default_value = "115200,9600"
    )]
    pub baud: Vec<u32>,
    /// The mosquitto binary.
    #[arg(long, value_name = "PATH", default_value = crate::bench::harness::DEFAULT_MOSQUITTO)]
    pub mosquitto: PathBuf,
}

pub fn run_bench(args: Args) -> anyhow::Result<ExitCode> {
    let started = Instant::now();
    let binary = std::env::current_exe().context("finding this binary")?;
    if !args.mosquitto.exists() {
        anyhow::bail!(
            "{} not found: the benchmarks need a real broker (apt-get install mosquitto, or \
             --mosquitto PATH)",
            args.mosquitto.display()
        );
    }
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let options = BenchOptions {
        binary: binary.clone(),
        quick: args.quick,
        only: args.only.clone(),
        bauds: args.baud.clone(),
    };
    let specs = plan(&options);
    let mut results: Vec<RunResult> = Vec::new();
    for (index, spec) in specs.iter().enumerate() {
        eprintln!(
            "[{:>3.0} s] run {}/{}: {}",
            started.elapsed().as_secs_f64(),
            index + 1,
            specs.len(),
            spec.label
        );
        let result = run(&binary, spec);
        eprintln!(
            "        {} changes, {} published, {} lost, p50 {} ms, p99 {} ms, daemon CPU {:.0} ms{}",
            result.report.changes,
            result.report.matched,
            result.report.lost,
            result.percentile_ms(0.5).map_or("–".into(), |v| format!("{v:.1}")),
            result.percentile_ms(0.99).map_or("–".into(), |v| format!("{v:.1}")),
            result.daemon_cpu.as_secs_f64() * 1e3,
            result
                .problem
                .as_deref()
                .map(|p| format!(" — {}", p.lines().next().unwrap_or("")))
                .unwrap_or_default()
        );
        results.push(result);
    }
    let mut scans = Vec::new();
    if args.only.is_empty() || args.only.contains(&5) {
        let buses = [
            ("6 devices at 3 settings", devices_at_three_settings()),
            ("empty bus", Vec::new()),
        ];
        for (label, devices) in buses {
            eprintln!("[{:>3.0} s] scan: {label}", started.elapsed().as_secs_f64());
            let scan = run_scan(&binary, &args.mosquitto, label, &devices);
            eprintln!(
                "        {} of {} devices found, {} settings ({} transmissions) in {:.2} s \
                 (wire floor {:.2} s){}",
                scan.devices_found,
                scan.devices_on_bus,
                scan.settings_scanned,
                scan.transmissions,
                scan.elapsed.as_secs_f64(),
                scan.wire_floor.as_secs_f64(),
                scan.problem
                    .as_deref()
                    .map(|p| format!(" — {}", p.lines().next().unwrap_or("")))
                    .unwrap_or_default()
            );
            scans.push(scan);
        }
    }
    let mut bare = Vec::new();
    if args.only.is_empty() || args.only.contains(&7) {
        // The floor under scenario 7's CPU per transaction, on the same bus, in the same run.
        for &baud in &args.baud {
            use crate::bench::bare_master::FloorMaster::{DaemonTransport, OneSleep, TwoSleeps};
            let rounds: &[(FloorMaster, usize)] = match (baud, args.quick) {
                (115_200, false) => &[(TwoSleeps, 300), (OneSleep, 300), (DaemonTransport, 300)],
                (115_200, true) => &[(TwoSleeps, 100), (OneSleep, 100), (DaemonTransport, 100)],
                // At 9600 the daemon's transport would still be learning its replies' timing
                // (read as they come) after the few transactions there is time for.
                (_, false) => &[(TwoSleeps, 40)],
                (_, true) => &[(TwoSleeps, 8)],
            };
            for &(master, transactions) in rounds {
                eprintln!(
                    "[{:>3.0} s] floor at {baud}: {master}",
                    started.elapsed().as_secs_f64()
                );
                let run = run_bare_master(&binary, &args.mosquitto, baud, 8, master, transactions);
                eprintln!(
                    "        {} of {} answered, {} µs and {} wake-ups per transaction{}",
                    run.answered,
                    run.transactions,
                    run.cpu_per_transaction_us()
                        .map_or("–".into(), |v| format!("{v:.0}")),
                    run.wake_ups_per_transaction()
                        .map_or("–".into(), |v| format!("{v:.2}")),
                    run.problem
                        .as_deref()
                        .map(|p| format!(" — {}", p.lines().next().unwrap_or("")))
                        .unwrap_or_default()
                );
                bare.push(run);
            }
        }
    }
    let plotted = if plots::load_font() {
        write_plots(&args.out, &results)
    } else {
        Err(anyhow::anyhow!(
            "no DejaVu Sans font found (apt-get install fonts-dejavu-core): no plots"
        ))
    };
    let environment = Environment {
        date_utc: crate::bench::report_date::utc_minute(std::time::SystemTime::now()),
        machine: machine(),
        commit: commit(),
        total: started.elapsed(),
        quick: args.quick,
    };
    let mut text = markdown(&results, &scans, &bare, &environment);
    if let Err(err) = &plotted {
        text.push_str(&format!("\nPlots: {err:#}\n"));
    }
    let report = args.out.join("latest.md");
    std::fs::write(&report, text).with_context(|| format!("writing {}", report.display()))?;
    eprintln!(
        "wrote {} in {:.0} s",
        report.display(),
        started.elapsed().as_secs_f64()
    );
    Ok(ExitCode::SUCCESS)
}

fn write_plots(out: &Path, results: &[RunResult]) -> anyhow::Result<()> {
    let mut bauds: Vec<u32> = results.iter().map(|r| r.baud).collect();
    bauds.sort_unstable();
    bauds.dedup();
    for baud in bauds.iter().rev() {
        let series = |scenario: u8| -> Vec<(String, &[u64])> {
            results
                .iter()
                .filter(|r| r.scenario == scenario && r.baud == *baud)
                .filter(|r| !r.report.latencies_ns.is_empty())
                .map(|r| {
                    let name = if r.fast_modbus {
                        "Fast Modbus"
                    } else {
                        "classic only"
                    };
                    (name.to_string(), r.report.latencies_ns.as_slice())
                })
                .collect()
        };
        let s2 = series(2);
        if !s2.is_empty() {
            let title = format!("Event latency under load: 32 devices, {baud} 8N2");
            plots::histogram(&out.join(format!("s2-{baud}-hist.png")), &title, &s2)?;
            plots::cdf(&out.join(format!("s2-{baud}-cdf.png")), &title, &s2)?;
        }
        let s1 = series(1);
        if !s1.is_empty() {
            let title = format!("Idle bus: 8 devices, events only, {baud} 8N2");
            plots::histogram(&out.join(format!("s1-{baud}-hist.png")), &title, &s1)?;
        }
    }
    let tradeoff: Vec<(u64, f64, f64)> = results
        .iter()
        .filter(|r| r.scenario == 3)
        .filter_map(|r| {
            Some((
                r.event_interval_ms?,
                r.percentile_ms(0.99)?,
                r.registers_per_s()?,
            ))
        })
        .collect();
    if !tradeoff.is_empty() {
        plots::tradeoff(&out.join("s3-tradeoff.png"), &tradeoff)?;
    }
    Ok(())
}

fn machine() -> String {
    let cpuinfo = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
    let model = cpuinfo
        .lines()
        .find_map(|l| l.strip_prefix("model name"))
        .and_then(|l| l.split(':').nth(1))
        .map_or("unknown CPU".to_string(), |m| m.trim().to_string());
    let cores = std::thread::available_parallelism().map_or(0, |n| n.get());
    let load = std::fs::read_to_string("/proc/loadavg")
        .ok()
        .and_then(|l| l.split_whitespace().next().map(str::to_string))
        .unwrap_or_default();
    let kernel = std::fs::read_to_string("/proc/sys/kernel/osrelease").unwrap_or_default();
    format!(
        "{model}, {cores} cores, load {load} at start, Linux {}",
        kernel.trim()
    )
}

fn commit() -> String {
    std::process::Command::new("git")
        .args(["rev-parse", "--short", "HEAD"])
        .output()
        .ok()
        .filter(|o| o.status.success())
        .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
        .unwrap_or_else(|| "unknown".into())
}
