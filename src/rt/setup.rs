//! Optional real-time process setup. Each step falls back with a warning (returned as
//! data, printed by the caller) where the OS does not permit it, e.g. EPERM as non-root.

/// What to ask of the OS before a loop starts.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct RtSetup {
    /// `mlockall(MCL_CURRENT | MCL_FUTURE)` so page faults cannot stall the loop.
    pub lock_memory: bool,
    /// SCHED_FIFO priority (1-99) for the calling thread.
    pub fifo_priority: Option<i32>,
    /// CPUs the calling thread may run on.
    pub cpus: Vec<usize>,
}

/// Applies `setup` to the calling thread/process and marks the thread real-time (its small
/// allocations from now on come from `rt::pool`); returns one warning per step refused.
pub fn apply_rt_setup(setup: &RtSetup) -> Vec<String> {
    super::pool::mark_this_thread_realtime();
    let mut warnings = Vec::new();
    if setup.lock_memory {
        // SAFETY: plain syscall with constant flags.
        let rc = unsafe { libc::mlockall(libc::MCL_CURRENT | libc::MCL_FUTURE) };
        if rc != 0 {
            warnings.push(format!(
                "mlockall refused ({}): memory not locked",
                std::io::Error::last_os_error()
            ));
        }
    }
    if let Some(priority) = setup.fifo_priority {
        if !(1..=99).contains(&priority) {
            warnings.push(format!(
                "SCHED_FIFO priority {priority} outside 1-99: not applied"
            ));
        } else {
            let param = libc::sched_param {
                sched_priority: priority,
            };
            // SAFETY: pid 0 is the calling thread; `param` is valid.
            let rc = unsafe { libc::sched_setscheduler(0, libc::SCHED_FIFO, &param) };
            if rc != 0 {
                warnings.push(format!(
                    "SCHED_FIFO priority {priority} refused ({}): running with normal scheduling",
                    std::io::Error::last_os_error()
                ));
            }
        }
    }
    if !setup.cpus.is_empty() {
        // Count the machine's CPUs, not `available_parallelism()`: that reports the
        // caller's current affinity, so a thread or child process that inherited a
        // one-CPU mask could never be moved to another CPU.
        // SAFETY: sysconf with a constant name has no preconditions.
        let n_cpus = unsafe { libc::sysconf(libc::_SC_NPROCESSORS_CONF) }.max(1) as usize;
        // SAFETY: cpu_set_t is plain data; CPU_ZERO/CPU_SET write within it.
        let mut set: libc::cpu_set_t = unsafe { std::mem::zeroed() };
        let mut any = false;
        for &cpu in &setup.cpus {
            if cpu >= n_cpus {
                warnings.push(format!(
                    "CPU {cpu} does not exist (this machine has {n_cpus}): ignored"
                ));
                continue;
            }
            unsafe { libc::CPU_SET(cpu, &mut set) };
            any = true;
        }
        if any {
            // SAFETY: pid 0 is the calling thread; `set` is a valid cpu_set_t.
            let rc =
                unsafe { libc::sched_setaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &set) };
            if rc != 0 {
                warnings.push(format!(
                    "CPU affinity {:?} refused ({}): not pinned",
                    setup.cpus,
                    std::io::Error::last_os_error()
                ));
            }
        }
    }
    warnings
}

/// Parses a CPU list like `0`, `0,1` or `0-3`.
pub fn parse_cpu_list(text: &str) -> Result<Vec<usize>, String> {
    let mut cpus = Vec::new();
    for part in text.split(',').map(str::trim).filter(|p| !p.is_empty()) {
        if let Some((a, b)) = part.split_once('-') {
            let (a, b): (usize, usize) = (
                a.trim()
                    .parse()
                    .map_err(|_| format!("`{part}`: not a CPU range"))?,
                b.trim()
                    .parse()
                    .map_err(|_| format!("`{part}`: not a CPU range"))?,
            );
            if a > b {
                return Err(format!("`{part}`: range runs backwards"));
            }
            cpus.extend(a..=b);
        } else {
            cpus.push(
                part.parse()
                    .map_err(|_| format!("`{part}`: not a CPU number"))?,
            );
        }
    }
    Ok(cpus)
}
