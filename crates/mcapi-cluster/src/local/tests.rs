//! The backoff, the setup's refusals and the state file.

use std::ffi::OsString;
use std::path::Path;
use std::time::{Duration, Instant};

use mcapi_shards::ReplicaName;
use mcapi_shards::plan;

use super::process::{Event, Process, Run};
use super::setup::{self, local_map};
use super::*;

#[test]
fn the_backoff_doubles_to_its_cap_and_resets_after_a_steady_run() {
    let b = Backoff::DEFAULT;
    let quick = Duration::from_secs(1);
    let mut streak = 0;
    let mut waits = Vec::new();
    for _ in 0..10 {
        let (wait, s) = b.after_exit(quick, streak);
        streak = s;
        waits.push(wait.as_millis());
    }
    assert_eq!(
        waits,
        [250, 500, 1000, 2000, 4000, 8000, 16000, 30000, 30000, 30000]
    );
    assert_eq!(b.after_exit(b.steady, streak), (b.first, 1));
    // A streak as long as u32 allows neither overflows nor exceeds the cap.
    assert_eq!(b.after_exit(quick, u32::MAX), (b.max, u32::MAX));
}

fn process(dir: &Path, program: &str, args: &[&str]) -> Process {
    Process {
        name: "p".into(),
        program: program.into(),
        args: args.iter().map(OsString::from).collect(),
        env: Vec::new(),
        log: dir.join("p.log"),
        listen: None,
        ready_url: String::new(),
        run: Run::Stopped,
        streak: 0,
        restarts: 0,
    }
}

/// Ticks until `event` matches or 10 s pass.
fn tick_until(p: &mut Process, b: &Backoff, want: fn(&Event) -> bool) -> Event {
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        if let Some(e) = p.tick(Instant::now(), b)
            && want(&e)
        {
            return e;
        }
        assert!(Instant::now() < deadline, "no such event within 10 s");
        std::thread::sleep(Duration::from_millis(10));
    }
}

#[test]
fn a_process_that_exits_is_started_again_after_its_backoff() {
    let dir = tempfile::tempdir().expect("tempdir");
    let b = Backoff {
        first: Duration::from_millis(30),
        max: Duration::from_millis(60),
        steady: Duration::from_secs(60),
    };
    let mut p = process(dir.path(), "/bin/sh", &["-c", "echo ran >&2; exit 3"]);
    let first = p.spawn().expect("spawns");
    let e = tick_until(&mut p, &b, |e| matches!(e, Event::Exited { .. }));
    let Event::Exited { status, wait, .. } = e else {
        unreachable!("matched above")
    };
    assert_eq!(status.code(), Some(3));
    assert_eq!(wait, b.first);
    assert!(p.pid().is_none(), "no pid while waiting");
    let e = tick_until(&mut p, &b, |e| matches!(e, Event::Restarted { .. }));
    let Event::Restarted { pid } = e else {
        unreachable!("matched above")
    };
    assert_ne!(pid, first);
    assert_eq!(p.restarts, 1);
    let e = tick_until(&mut p, &b, |e| matches!(e, Event::Exited { .. }));
    assert!(
        matches!(e, Event::Exited { wait, .. } if wait == b.max),
        "second quick exit: the doubled wait, capped: {e:?}"
    );
    // The log gathers every run's stderr.
    std::thread::sleep(Duration::from_millis(50));
    assert_eq!(p.log_tail().lines().filter(|l| *l == "ran").count(), 2);

    let mut missing = process(dir.path(), "/nonexistent/program", &[]);
    missing.run = Run::Waiting {
        until: Instant::now(),
    };
    let e = missing.tick(Instant::now(), &b).expect("an event");
    assert!(
        matches!(&e, Event::SpawnFailed { error, .. } if error.contains("/nonexistent/program")),
        "{e:?}"
    );
}

#[test]
fn a_data_dir_keeps_its_map_and_refuses_another_replica_count() {
    let dir = tempfile::tempdir().expect("tempdir");
    let map = local_map(dir.path(), Some(2)).expect("planned");
    assert_eq!(map.replicas().len(), 2);
    let again = local_map(dir.path(), None).expect("reused");
    assert_eq!(again.to_text(), map.to_text());
    let e = local_map(dir.path(), Some(3)).expect_err("2 is not 3");
    assert!(
        format!("{e:#}").contains("has 2 replicas (mcapi-0, mcapi-1), not 3"),
        "{e:#}"
    );
    let fresh = tempfile::tempdir().expect("tempdir");
    assert_eq!(
        local_map(fresh.path(), None)
            .expect("default")
            .replicas()
            .len(),
        DEFAULT_REPLICAS
    );
    // A replica may not take the router's name (its log would be the router's).
    let odd = tempfile::tempdir().expect("tempdir");
    let names = ["haproxy", "mcapi-1"].map(|n| ReplicaName::parse(n).expect("name"));
    let map = plan::plan(&names, None).expect("plan").map;
    std::fs::write(odd.path().join(MAP_FILE), map.to_text()).expect("write");
    let e = local_map(odd.path(), None).expect_err("haproxy");
    assert!(
        format!("{e:#}").contains("`haproxy` names the router"),
        "{e:#}"
    );
}

#[test]
fn netns_placements_are_checked_before_anything_starts() {
    use super::netns::Placements;
    let refused = |spec: &str| {
        format!(
            "{:#}",
            Placements::parse(&[spec.to_string()]).expect_err(spec)
        )
    };
    assert!(refused("mcapi-0").contains("expected NAME=NETNS@IP"));
    assert!(refused("mcapi-0=ns0").contains("needs the address it listens on there"));
    assert!(refused("mcapi-0=ns0@10.1.2").contains("is not an IP address"));
    assert!(refused("mcapi-0=ns0@0.0.0.0").contains("cannot be dialled"));
    assert!(refused("haproxy=ns0@10.1.2.3").contains("listens on --http and --grpc"));
    assert!(refused("Mcapi_0=ns0@10.1.2.3").contains("Mcapi_0"));
    assert!(refused("mcapi-0=../x@10.1.2.3").contains("is not a namespace name"));
    assert!(
        refused("mcapi-0=mcapi-no-such-netns@10.1.2.3")
            .contains("no network namespace `mcapi-no-such-netns`")
    );
    // None given: every process on loopback, as before, and run as is.
    let none = Placements::parse(&[]).expect("none");
    assert_eq!(none.host("mcapi-0").to_string(), "127.0.0.1");
    let (program, args) = none.command("mcapi-0", "/bin/mcapi".into(), vec!["serve".into()]);
    assert_eq!(program, std::path::PathBuf::from("/bin/mcapi"));
    assert_eq!(args, [OsString::from("serve")]);
}

/// Held by the tests that find ports free by binding port 0 and release
/// them: run side by side, one would be handed the ports the other just
/// released, and see them taken.
static PORTS: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn ports_lock() -> std::sync::MutexGuard<'static, ()> {
    PORTS
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

#[test]
fn the_routers_ports_are_never_handed_to_a_replica() {
    let _ports = ports_lock();
    let [http, grpc]: [u16; 2] = setup::free_ports(2, &[])
        .expect("two ports")
        .try_into()
        .expect("two");
    let addr = |port| std::net::SocketAddr::from(([127, 0, 0, 1], port));
    let held = setup::hold_router_addresses(addr(http), addr(grpc)).expect("free");
    // Held: a second cluster on them is refused, naming the flag...
    let err = setup::hold_router_addresses(addr(http), addr(grpc))
        .expect_err("--http is taken")
        .to_string();
    assert!(
        err.contains("--http 127.0.0.1:") && err.contains("is not free"),
        "{err}"
    );
    // ...and a thousand replica ports chosen meanwhile never include them.
    for _ in 0..5 {
        let ports = setup::free_ports(200, &[]).expect("ports");
        assert!(!ports.contains(&http) && !ports.contains(&grpc));
    }
    drop(held);
    setup::hold_router_addresses(addr(http), addr(grpc)).expect("free again once dropped");
}

#[test]
fn replica_ports_come_from_below_the_ephemeral_range() {
    let _ports = ports_lock();
    let Some(low) = setup::ephemeral_start().filter(|&low| low >= 4096) else {
        return; // this machine's range leaves no room: ports come from port 0
    };
    let ports = setup::free_ports(64, &[]).expect("ports");
    assert!(ports.iter().all(|&p| p >= low / 2 && p < low), "{ports:?}");
    let (again, third) = (
        setup::free_ports(64, &[]).expect("ports"),
        setup::free_ports(64, &[]).expect("ports"),
    );
    assert!(
        ports != again || again != third,
        "every call starts somewhere else"
    );
}

#[test]
fn ports_of_replicas_down_for_a_moment_are_not_handed_out() {
    let _ports = ports_lock();
    // Ports the kernel is about to hand out again: found free and released.
    let taken = setup::free_ports(64, &[]).expect("ports");
    for _ in 0..5 {
        let ports = setup::free_ports(100, &taken).expect("ports");
        assert_eq!(ports.len(), 100);
        assert!(ports.iter().all(|p| !taken.contains(p)), "{ports:?}");
        let distinct: std::collections::BTreeSet<_> = ports.iter().collect();
        assert_eq!(distinct.len(), 100);
    }
}
