//! boltwatch: structural health monitoring of bolted connections by FE model updating.
//!
//! See `README.md` for a tour, `docs/` for the user guide, and `docs/paper.md` for the
//! function implementing each equation of the paper.

pub mod commands;
pub mod contract;
pub mod core;
pub mod daemon;
pub mod draw;
pub mod io;
pub mod pipeline;
pub mod plot;
pub mod scenario;
pub mod settings;

/// Opts this process out of transparent huge pages (Linux; elsewhere nothing). The
/// allocator asks for them on its arena, and every first touch of a 2 MiB page then zeroes
/// all of it: `boltwatch modes -n 12` on the four-bay solid frame spent a third to half of
/// its time in the kernel doing that, 1.28–1.76 s with huge pages against 1.00–1.22 s
/// without (three runs each, after another process had used and freed 3 GB). Called first
/// thing by the binary and the benchmarks.
pub fn no_transparent_huge_pages() {
    #[cfg(target_os = "linux")]
    // SAFETY: PR_SET_THP_DISABLE only sets a flag of the calling process; it reads no memory.
    unsafe {
        libc::prctl(libc::PR_SET_THP_DISABLE, 1, 0, 0, 0);
    }
}

/// mimalloc instead of the system allocator: the tracking path allocates and frees many
/// short-lived vectors and matrices per modal set, and glibc's malloc spent ~10 % of a
/// replay in consolidating free chunks (measured with `perf`, issue 4).
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// Returns the memory the allocator holds freed to the system at once (mimalloc purges
/// freed memory only after a delay, when a later allocation gives it the chance).
pub fn release_free_memory() {
    // SAFETY: mi_collect only walks the allocator's own structures; no memory of ours is
    // read or written.
    unsafe { libmimalloc_sys::mi_collect(true) }
}

/// Scratch below this many bytes is left to the allocator rather than returned to the
/// system ([`release_scratch`]).
pub const RELEASE_SCRATCH_FROM_BYTES: u64 = 16 << 20;

/// [`release_free_memory`] after a step that freed about `scratch` bytes, when they are
/// at least [`RELEASE_SCRATCH_FROM_BYTES`]: the four-bay solid frame's assembly and
/// ordering free hundreds of MB that later allocations of other sizes would not reuse;
/// a small model's free a few MB, which the next model reuses. Releasing those too made
/// `diagnose` on the space frame (a model built for every candidate and profile point)
/// fault every page back in: 2.1 million minor page faults and 15 s of its 120 s of CPU
/// in the kernel.
pub fn release_scratch(scratch: u64) {
    if scratch >= RELEASE_SCRATCH_FROM_BYTES {
        release_free_memory();
    }
}
