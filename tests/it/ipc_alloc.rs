//! What the loop's per-sample iceoryx2 calls allocate, counted on this thread (iceoryx2
//! 0.10): the one heap block a publish makes inside iceoryx2, and none for a receive, a
//! notify or the controller's wait on its listener (a `WaitSet` allocated two blocks per
//! wake-up). The loops' own code allocates nothing (`hil_core`, `model_alloc`); this is
//! what the transport adds, stated in ARCHITECTURE.md. The UDP link's datagram path
//! (encode, send, receive, decode, check) allocates nothing.

use crate::alloc_counter::{count_allocations, count_allocations_and_system};
use crate::common::{law_command, sample};
use fastemu::ipc::{quiet_iceoryx2_logs, IpcNode};
use fastemu::link::protocol::{CommandDatagram, Datagram, SampleDatagram, Side};
use fastemu::link::socket::{bound_loopback_pair, open_link_socket, Receive};
use std::time::Duration;

/// The run's iceoryx2 files in /dev/shm.
fn shm_files(run_id: &str) -> Vec<String> {
    let prefix = fastemu::ipc::file_prefix(run_id);
    std::fs::read_dir("/dev/shm")
        .map(|d| {
            d.filter_map(|e| e.ok()?.file_name().into_string().ok())
                .filter(|n| n.starts_with(&prefix))
                .collect()
        })
        .unwrap_or_default()
}

/// Clears the run's iceoryx2 files when dropped: on every exit path, a failed assertion
/// too (declared before the nodes, it drops after them).
struct ClearRun(String);

impl Drop for ClearRun {
    fn drop(&mut self) {
        let _ = fastemu::ipc::cleanup::clear_run(&self.0);
    }
}

#[test]
fn a_publish_allocates_one_block_inside_iceoryx2_and_a_receive_a_notify_or_a_wait_none() {
    quiet_iceoryx2_logs();
    let run_id = format!("italloc{}", std::process::id());
    let _clear = ClearRun(run_id.clone());
    const N: u64 = 1000;
    let (publishes, receives, wakes, received) = {
        let node = IpcNode::new(&run_id, "alloc").unwrap();
        let out = node.displacement_out().unwrap();
        let input = node.displacement_in().unwrap();
        let wake = node.setpoint_wake().unwrap();
        let listener = node.setpoint_listener().unwrap();
        // Warm-up: the first send and receive set up the connection.
        for k in 0..8 {
            assert!(out.publish(sample(k, 4.2e-4)));
            wake.notify();
        }
        input.receive_each(|_| {});
        let publishes = count_allocations(|| {
            for k in 0..N {
                out.publish(sample(100 + k, 4.2e-4));
            }
        });
        let mut received = 0u64;
        let receives = count_allocations(|| input.receive_each(|s| received += s.sequence));
        let wakes = count_allocations(|| {
            for _ in 0..N {
                wake.notify();
            }
        });
        // The controller's wait on its listener: woken by a pending notification, which
        // it consumes (the next wait, with none pending, times out unwoken) ...
        let pending = count_allocations(|| {
            for _ in 0..N {
                wake.notify();
                assert!(listener.wait_for(Duration::from_millis(100)));
            }
            assert!(!listener.wait_for(Duration::from_micros(300)));
        });
        // ... and asleep, woken by another thread's notifications (its own node; only
        // this thread's allocations are counted).
        const WOKEN: usize = 100;
        let id = run_id.clone();
        let notifier = std::thread::spawn(move || {
            let node = IpcNode::new(&id, "notifier").unwrap();
            let wake = node.setpoint_wake().unwrap();
            for _ in 0..WOKEN {
                std::thread::sleep(Duration::from_micros(500));
                wake.notify();
            }
        });
        let mut woken = 0;
        let asleep = count_allocations(|| {
            while woken < WOKEN {
                if listener.wait_for(Duration::from_millis(200)) {
                    woken += 1;
                } else {
                    break;
                }
            }
        });
        notifier.join().unwrap();
        // Notifications close together may be consumed by one wake-up: at least a few.
        assert!(woken >= 10, "{woken} wake-ups of {WOKEN} notifications");
        (publishes, receives, wakes + pending + asleep, received)
    };
    // Every sample arrived, in order, once: the sum of 100..100+N.
    assert_eq!(received, (100..100 + N).sum::<u64>());
    // iceoryx2 0.10 allocates one small block per loan (the sample's shared state, an
    // `Rc`) and frees it when the sample is sent: one per publish, no more.
    assert_eq!(publishes, N as usize, "allocations in {N} publishes");
    assert_eq!(receives, 0, "allocations in receiving {N} samples");
    assert_eq!(wakes, 0, "allocations in {N} notifications and waits");
    // Nothing left behind but iceoryx2's node counter, which the run's cleanup removes.
    let left = fastemu::ipc::cleanup::clear_run(&run_id);
    assert!(left.is_empty(), "{left:?}");
    assert!(shm_files(&run_id).is_empty(), "{:?}", shm_files(&run_id));
}

/// On a thread marked real-time (every loop thread is, by `apply_rt_setup`), iceoryx2's
/// block per publish comes from the fixed pool (`fastemu::rt::pool`): the N requests are
/// there, none reaches the system allocator, and the samples arrive.
#[test]
fn on_a_real_time_thread_a_publishs_block_comes_from_the_pool_not_the_system() {
    quiet_iceoryx2_logs();
    let run_id = format!("itpool{}", std::process::id());
    let _clear = ClearRun(run_id.clone());
    const N: u64 = 1000;
    let id = run_id.clone();
    let (counts, received) = std::thread::spawn(move || {
        let node = IpcNode::new(&id, "pool").unwrap();
        let out = node.displacement_out().unwrap();
        let input = node.displacement_in().unwrap();
        for k in 0..8 {
            assert!(out.publish(sample(k, 4.2e-4)));
        }
        input.receive_each(|_| {});
        fastemu::rt::pool::mark_this_thread_realtime();
        let counts = count_allocations_and_system(|| {
            for k in 0..N {
                out.publish(sample(100 + k, 4.2e-4));
            }
        });
        let mut received = 0u64;
        input.receive_each(|s| received += s.sequence);
        (counts, received)
    })
    .join()
    .unwrap();
    assert_eq!(received, (100..100 + N).sum::<u64>());
    assert_eq!(
        counts,
        (N as usize, 0),
        "(requests, reaching the system) in {N} publishes"
    );
}

#[test]
fn the_udp_links_datagram_path_allocates_nothing() {
    let (fastemu_socket, rig_socket) = bound_loopback_pair().unwrap();
    let (fastemu_addr, rig_addr) = (
        fastemu_socket.local_addr().unwrap(),
        rig_socket.local_addr().unwrap(),
    );
    let (mut to_rig, mut from_rig) =
        open_link_socket(fastemu_socket, rig_addr, Side::Fastemu, None).unwrap();
    let (mut to_fastemu, mut from_fastemu) =
        open_link_socket(rig_socket, fastemu_addr, Side::Rig, None).unwrap();
    const N: u64 = 1000;
    let mut accepted = [0u64; 2];
    // Loopback delivers at once: every datagram sent is read in the same round.
    let mut round = |k: u64, accepted: &mut [u64; 2]| {
        to_fastemu.send_sample(&SampleDatagram::of(&sample(k, 4.2e-4), 0, 0));
        if let Receive::Accepted(r) = from_rig.receive() {
            assert!(matches!(r.datagram, Datagram::Sample(s) if s.to_sample(0).sequence == k));
            accepted[0] += 1;
        }
        to_rig.send_command(&CommandDatagram {
            command: law_command(k),
            echo_sample_time_ns: 0,
        });
        if let Receive::Accepted(r) = from_fastemu.receive() {
            assert!(matches!(r.datagram, Datagram::Command(c) if c.command.sequence == k));
            accepted[1] += 1;
        }
    };
    for k in 0..8 {
        round(k, &mut accepted);
    }
    let allocations = count_allocations(|| {
        for k in 8..8 + N {
            round(k, &mut accepted);
        }
    });
    assert_eq!(
        accepted,
        [N + 8, N + 8],
        "datagrams accepted (samples, commands)"
    );
    assert_eq!(
        allocations, 0,
        "allocations in {N} rounds of a sample and a command"
    );
}
