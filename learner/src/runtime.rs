//! Process-wide CPU settings for the SAC maths.
//! Call [`configure_cpu`] once, early, in a process that runs SAC updates on the CPU.
//!
//! * **Threads**: libtorch's intra-op thread count (`tch::set_num_threads`).
//! * **Allocator**: libtorch takes every activation and gradient (MBs each) from `malloc`. glibc
//!   serves such blocks with fresh `mmap`s (its dynamic mmap threshold starts at 128 KiB) and trims
//!   the heap top eagerly, so each update faults its working set back in page by page: about 15-25 %
//!   of an update's CPU time here. Raising `M_MMAP_THRESHOLD` to glibc's 32 MiB maximum and
//!   `M_TRIM_THRESHOLD` to 1 GiB keeps that memory in the heap between updates.
//!   One arena (`M_ARENA_MAX` 1) keeps it there for every thread: glibc gives other threads
//!   arenas of 64 MiB heaps and unmaps a heap as soon as all its blocks are free, whatever the
//!   trim threshold, so a member thread whose arena's first heap is fragmented faulted a fresh
//!   heap in and unmapped it again at every update (about 20 times a second in a PickCube
//!   run's stage 2, where the kernel's share of the learner's CPU time rose from 3 % to 14 %).
//!   [`tune_allocator`] sets it first thing in `main`, before any other thread has an arena.
//!
//! Not settable from here: OpenMP's wait policy. libgomp reads `OMP_WAIT_POLICY` when it loads,
//! before `main`; with more than one thread on cores that other processes also use, its spinning
//! barriers make an update several times slower. The process's launcher should set
//! `OMP_WAIT_POLICY=PASSIVE` (or use one thread) where the learner shares cores with actors.

/// What [`configure_cpu`] applied.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CpuRuntime {
    pub threads: i32,
    /// Whether the glibc allocator settings were applied (false on other C libraries).
    pub allocator_tuned: bool,
}

/// Sets libtorch's thread count and tunes glibc's allocator for libtorch's large, short-lived
/// blocks (see the module docs).
pub fn configure_cpu(threads: i32) -> CpuRuntime {
    tch::set_num_threads(threads);
    CpuRuntime {
        threads: tch::get_num_threads(),
        allocator_tuned: tune_allocator(),
    }
}

/// glibc's allocator settings for libtorch's blocks (see the module docs); true when applied,
/// false on other C libraries. Call it first thing in `main`, before other threads start: the
/// one-arena setting only stops arenas from being created, it does not take away those that
/// threads already have. [`configure_cpu`] applies it again (harmless) for processes that start
/// no threads first.
pub fn tune_allocator() -> bool {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        const MMAP_THRESHOLD_MAX: libc::c_int = 32 << 20;
        const TRIM_THRESHOLD: libc::c_int = 1 << 30;
        // SAFETY: mallopt only changes glibc's allocation settings; it takes no pointers and is
        // thread-safe (it takes the arena locks).
        unsafe {
            libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD_MAX) == 1
                && libc::mallopt(libc::M_TRIM_THRESHOLD, TRIM_THRESHOLD) == 1
                && libc::mallopt(libc::M_ARENA_MAX, 1) == 1
        }
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    {
        false
    }
}

/// The instruction sets that run bf16 matrix products natively on this CPU, by Linux's
/// `/proc/cpuinfo` names (`amx_bf16`, `avx512_bf16`); empty where there are none, or where
/// the file cannot be read (then libtorch emulates bf16 products in f32, slower than f32 itself).
pub fn native_bf16() -> Vec<&'static str> {
    std::fs::read_to_string("/proc/cpuinfo")
        .map(|text| native_bf16_in(&text))
        .unwrap_or_default()
}

/// [`native_bf16`] of a `/proc/cpuinfo` text: the bf16 instruction sets its first `flags` line
/// names.
pub fn native_bf16_in(cpuinfo: &str) -> Vec<&'static str> {
    let flags: Vec<&str> = cpuinfo
        .lines()
        .find_map(|line| {
            let (key, value) = line.split_once(':')?;
            (key.trim() == "flags").then(|| value.split_whitespace().collect())
        })
        .unwrap_or_default();
    ["amx_bf16", "avx512_bf16"]
        .into_iter()
        .filter(|name| flags.contains(name))
        .collect()
}

#[cfg(test)]
mod tests {
    /// A Sapphire Rapids line has both, a Zen 4 line AVX512-BF16 only, a Zen 3 line neither;
    /// `amx_bf16` must be a whole flag, not a prefix of another.
    #[test]
    fn native_bf16_reads_the_flags_line() {
        let cpu = |flags: &str| format!("processor\t: 0\nmodel name\t: X\nflags\t\t: {flags}\n");
        assert_eq!(
            super::native_bf16_in(&cpu("fpu avx512f amx_bf16 amx_tile avx512_bf16 amx_int8")),
            ["amx_bf16", "avx512_bf16"]
        );
        assert_eq!(
            super::native_bf16_in(&cpu("fpu avx2 avx512f avx512_bf16")),
            ["avx512_bf16"]
        );
        assert!(super::native_bf16_in(&cpu("fpu avx2 fma amx_bf16x")).is_empty());
        assert!(super::native_bf16_in("no flags here").is_empty());
    }

    #[test]
    fn configure_cpu_sets_threads_and_tunes_glibc() {
        let applied = super::configure_cpu(1);
        assert_eq!(applied.threads, 1);
        assert_eq!(
            applied.allocator_tuned,
            cfg!(all(target_os = "linux", target_env = "gnu"))
        );
    }
}
