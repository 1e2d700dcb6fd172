//! glibc malloc settings for the binaries, which allocate and free buffers of a few MB to tens of MB at a high rate
//! (shard columns in the pipeline; activations, gradients and im2col blocks in the trainer). glibc's defaults
//! hand such buffers back to the kernel on free and map fresh ones on the next allocation, so the page faults,
//! zeroing and TLB shootdowns between threads (system time) cost more than the work. Measured per binary; the
//! figures are in its `main.rs`.

/// Allocator thresholds, bytes.
#[derive(Debug, Clone, Copy)]
pub struct MallocSettings {
    /// Allocations at least this large are mapped on their own (and unmapped on free); below it they come from
    /// the heap and are reused. glibc caps it at 32 MiB on 64-bit.
    pub mmap_threshold: usize,
    /// Free memory at the top of the heap beyond this is returned to the kernel.
    pub trim_threshold: usize,
    /// Most arenas (per-thread heaps); `None` leaves glibc's default (8 per core).
    pub arena_max: Option<usize>,
}

/// Apply `settings` (glibc on Linux only; a no-op elsewhere). Call first thing in `main`, before any thread starts.
pub fn tune(settings: MallocSettings) {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets allocator parameters; called once, before any other thread exists.
    unsafe {
        let clamp = |bytes: usize| bytes.min(i32::MAX as usize) as libc::c_int;
        libc::mallopt(libc::M_MMAP_THRESHOLD, clamp(settings.mmap_threshold));
        libc::mallopt(libc::M_TRIM_THRESHOLD, clamp(settings.trim_threshold));
        if let Some(arenas) = settings.arena_max {
            libc::mallopt(libc::M_ARENA_MAX, clamp(arenas));
        }
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    let _ = settings;
}
