//! Real processes over real shared memory: each test starts this test binary again as the other
//! side (`child_entry`, selected by an environment variable), so the two ends share nothing but
//! `/dev/shm`.
//!
//! * Transitions: a publisher bursts many more frames than the subscriber's queue holds into a
//!   slow subscriber; every frame arrives, in order, whole (back-pressure, never overwrite).
//! * Policies: a publisher publishes versions as fast as it can while a subscriber reads; the
//!   versions seen only grow, every one is whole (each byte is the one its version wrote), and the
//!   last one arrives.
use std::io::{BufRead, BufReader, Read, Write};
use std::process::{Child, ChildStdout, Command, Stdio};
use std::time::{Duration, Instant};

use rfcl_shm::frame::TransitionHeader;
use rfcl_shm::{
    new_run_id, PolicyHeader, PolicyLimits, PolicyPublisher, PolicySubscriber, Sent, ServiceNames,
    ShmNode, TransitionLimits, TransitionPublisher, TransitionSubscriber,
};

const ROLE: &str = "RFCL_SHM_TEST_ROLE";
const SERVICE: &str = "RFCL_SHM_TEST_SERVICE";

const FRAMES: u64 = 400;
const RECORDS_PER_FRAME: u32 = 10;
const RECORD_BYTES: usize = 24;

const VERSIONS: u64 = 2000;
const POLICY_BYTES: usize = 48 * 1024;

fn record_byte(frame: u64, i: usize) -> u8 {
    (frame.wrapping_mul(31) as usize + i * 7) as u8
}

fn policy_byte(version: u64, i: usize) -> u8 {
    (version.wrapping_mul(131) as usize ^ (i * 13)) as u8
}

/// Starts this test binary as `role`, with `service` to use; its stdin stays open until dropped.
/// Reads `child`'s stdout up to its "ready" line (the test harness prints its own lines first);
/// `who` names it when it exits first. Keep the reader: the child's later lines need the pipe.
fn wait_ready(child: &mut Child, who: &str) -> BufReader<ChildStdout> {
    let mut stdout = BufReader::new(child.stdout.take().unwrap());
    let mut line = String::new();
    while !line.trim_end().ends_with("ready") {
        line.clear();
        assert!(stdout.read_line(&mut line).unwrap() > 0, "{who} exited");
    }
    stdout
}

fn child(role: &str, service: &str) -> Child {
    Command::new(std::env::current_exe().unwrap())
        .args([
            "--exact",
            "child_entry",
            "--nocapture",
            "--test-threads",
            "1",
        ])
        .env(ROLE, role)
        .env(SERVICE, service)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .unwrap()
}

/// The child side. A no-op when run as an ordinary test.
#[test]
fn child_entry() {
    let Ok(role) = std::env::var(ROLE) else {
        return;
    };
    let service = std::env::var(SERVICE).unwrap();
    match role.as_str() {
        "transition-publisher" => {
            let (node, _) = ShmNode::create("shm-test", "publisher").unwrap();
            let mut publisher =
                TransitionPublisher::open(node, &service, RECORDS_PER_FRAME as usize, RECORD_BYTES)
                    .unwrap();
            for f in 0..FRAMES {
                let records: Vec<u8> = (0..RECORDS_PER_FRAME as usize * RECORD_BYTES)
                    .map(|i| record_byte(f, i))
                    .collect();
                // As the actor does: a frame that reached no subscriber (not connected yet, right
                // at the start) is sent again; it was not delivered, so nothing is doubled.
                while publisher
                    .send(5, 3, 2, RECORDS_PER_FRAME, &records)
                    .unwrap()
                    == Sent::NoSubscriber
                {
                    std::thread::sleep(Duration::from_millis(1));
                }
            }
            println!("sent {}", publisher.frames_sent());
        }
        "policy-publisher" => {
            let (node, _) = ShmNode::create("shm-test", "policy").unwrap();
            let publisher =
                PolicyPublisher::create(node, &service, PolicyLimits::default(), POLICY_BYTES)
                    .unwrap();
            println!("ready");
            std::io::stdout().flush().unwrap();
            // Wait for the reader to subscribe (it says so on stdin).
            let mut line = String::new();
            std::io::stdin().read_line(&mut line).unwrap();
            let mut weights = vec![0u8; POLICY_BYTES];
            for v in 1..=VERSIONS {
                for (i, b) in weights.iter_mut().enumerate() {
                    *b = policy_byte(v, i);
                }
                let header = PolicyHeader {
                    version: v,
                    learner_env_steps: v * 10,
                };
                publisher.publish(header, &weights).unwrap();
            }
            println!("published {VERSIONS}");
            std::io::stdout().flush().unwrap();
            // Keep the service until the reader is done (it closes stdin).
            let _ = std::io::stdin().read_to_end(&mut Vec::new());
        }
        "killed" => {
            // Holds a node and a service of run `service` until it is killed with SIGKILL.
            let (node, _) = ShmNode::create(&service, "victim").unwrap();
            let names = ServiceNames::new(&service, "1");
            let _subscriber =
                TransitionSubscriber::create(node, &names.transitions, TransitionLimits::default())
                    .unwrap();
            println!("ready");
            std::io::stdout().flush().unwrap();
            let _ = std::io::stdin().read_to_end(&mut Vec::new());
            std::thread::sleep(Duration::from_secs(600));
        }
        other => panic!("unknown role {other}"),
    }
}

fn wait_until<T>(what: &str, limit: Duration, mut probe: impl FnMut() -> Option<T>) -> T {
    let until = Instant::now() + limit;
    loop {
        if let Some(v) = probe() {
            return v;
        }
        assert!(Instant::now() < until, "{what}: not within {limit:?}");
        std::thread::sleep(Duration::from_millis(1));
    }
}

#[test]
fn a_burst_far_bigger_than_the_queue_arrives_whole_and_in_order() {
    let names = ServiceNames::new("shm-test", &new_run_id());
    let (node, _) = ShmNode::create("shm-test", "subscriber").unwrap();
    let limits = TransitionLimits {
        max_publishers: 2,
        queue_frames: 2,
    };
    let subscriber = TransitionSubscriber::create(node, &names.transitions, limits).unwrap();
    let publisher = child("transition-publisher", &names.transitions);

    let mut next = 0u64;
    while next < FRAMES {
        let frame = wait_until("the next frame", Duration::from_secs(60), || {
            subscriber.receive().unwrap()
        });
        let (header, records) = frame.decode().unwrap();
        assert_eq!(
            header,
            TransitionHeader {
                actor_id: 5,
                obs_dim: 3,
                action_dim: 2,
                count: RECORDS_PER_FRAME,
                seq: next,
                records_before: next * u64::from(RECORDS_PER_FRAME),
                ..header
            },
            "frames arrive in order, none missing"
        );
        assert_eq!(records.len(), RECORDS_PER_FRAME as usize * RECORD_BYTES);
        for (i, b) in records.iter().enumerate() {
            assert_eq!(*b, record_byte(next, i), "frame {next} byte {i}");
        }
        next += 1;
        // A slow reader: the publisher keeps finding the queue full.
        if next % 8 == 0 {
            std::thread::sleep(Duration::from_millis(2));
        }
    }
    let out = publisher.wait_with_output().unwrap();
    assert!(out.status.success());
    assert!(
        String::from_utf8_lossy(&out.stdout).contains(&format!("sent {FRAMES}")),
        "{}",
        String::from_utf8_lossy(&out.stdout)
    );
    assert!(subscriber.receive().unwrap().is_none(), "nothing extra");
}

#[test]
fn policy_versions_only_grow_and_are_never_torn() {
    let names = ServiceNames::new("shm-test", &new_run_id());
    let mut publisher = child("policy-publisher", &names.policy);
    let _stdout = wait_ready(&mut publisher, "the publisher");
    let (node, _) = ShmNode::create("shm-test", "policy-reader").unwrap();
    let subscriber = PolicySubscriber::open(node, &names.policy).unwrap();
    let mut stdin = publisher.stdin.take().unwrap();
    writeln!(stdin, "subscribed").unwrap();

    let (mut last, mut seen) = (0u64, 0u64);
    while last < VERSIONS {
        let frame = wait_until("a newer version", Duration::from_secs(60), || {
            subscriber.latest().unwrap()
        });
        let (header, weights) = frame.decode().unwrap();
        assert!(header.version > last, "{} after {last}", header.version);
        assert_eq!(header.learner_env_steps, header.version * 10);
        assert_eq!(weights.len(), POLICY_BYTES);
        let v = header.version;
        if let Some(i) = (0..POLICY_BYTES).find(|&i| weights[i] != policy_byte(v, i)) {
            panic!("version {v} is torn at byte {i}");
        }
        last = v;
        seen += 1;
    }
    assert!(seen >= 1);
    drop(stdin);
    assert!(publisher.wait().unwrap().success());
}

#[test]
fn opening_a_service_that_is_not_there_names_it() {
    let names = ServiceNames::new("shm-test", &new_run_id());
    let (node, _) = ShmNode::create("shm-test", "nobody").unwrap();
    let e = TransitionPublisher::open(node, &names.transitions, 1, 8).unwrap_err();
    let text = e.to_string();
    assert!(
        text.contains(&format!(
            "cannot open the iceoryx2 service '{}'",
            names.transitions
        )),
        "{text}"
    );
    let (node, _) = ShmNode::create("shm-test", "nobody").unwrap();
    let e = PolicySubscriber::open(node, &names.policy).unwrap_err();
    assert!(e.to_string().contains(&names.policy), "{e}");
}

#[test]
fn a_killed_processs_node_and_service_are_cleaned_up_by_the_next_process_of_its_run() {
    let run = format!("shm-test-kill-{}", new_run_id());
    let mut victim = child("killed", &run);
    let _stdout = wait_ready(&mut victim, "the victim");
    victim.kill().unwrap();
    victim.wait().unwrap();

    let (node, cleanup) = ShmNode::create(&run, "successor").unwrap();
    assert_eq!(cleanup.of_run, 1, "{cleanup:?}");
    assert_eq!(cleanup.failed, 0, "{cleanup:?}");
    // The dead process's service is gone with it: the same name can be created again.
    let names = ServiceNames::new(&run, "1");
    TransitionSubscriber::create(node, &names.transitions, TransitionLimits::default()).unwrap();
}
