//! A fixed pool of small heap blocks for threads marked real-time (`RtPool`, the processes'
//! global allocator): what their loops cannot avoid allocating (iceoryx2 0.10 allocates one
//! block per publish) comes from it without the system allocator, a lock or a system call.
//! Must not: grow, block, or serve threads not marked (they go to the system allocator).
//!
//! The pool is `BLOCKS` blocks of `BLOCK_BYTES` in the process's static memory and a bitmap
//! of atomic words: a block is taken by a compare-and-swap on its bit and given back by
//! clearing it, from any thread. A request on a marked thread that is larger than a block,
//! more aligned, or meets the pool full goes to the system allocator and is counted
//! (`PoolStats::fallbacks`); a block freed on any thread goes back to the pool. Why not a
//! crate: the real-time allocators checked (`rlsf`'s TLSF) serve one arena behind a lock or
//! per thread, and a block freed on another thread must still come home; this is the
//! smallest lock-free thing that does it (ARCHITECTURE.md).

use std::alloc::{GlobalAlloc, Layout};
use std::cell::{Cell, UnsafeCell};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};

/// Size and alignment of a block, bytes (iceoryx2 0.10's block per publish is 48 bytes).
pub const BLOCK_BYTES: usize = 128;
/// Blocks in the pool (512 KiB): a loop holds one at a time; the rest is for what the
/// marked threads allocate before their loops and keep.
pub const BLOCKS: usize = 4096;
const WORDS: usize = BLOCKS / 64;

#[repr(C, align(128))]
struct Block([u8; BLOCK_BYTES]);

struct Memory(UnsafeCell<[Block; BLOCKS]>);

// SAFETY: a block is only ever handed to one owner at a time (its bit, set by a successful
// compare-and-swap, is the ownership); the pool itself never reads or writes the bytes.
unsafe impl Sync for Memory {}

static MEMORY: Memory = Memory(UnsafeCell::new([const { Block([0; BLOCK_BYTES]) }; BLOCKS]));
static USED: [AtomicU64; WORDS] = [const { AtomicU64::new(0) }; WORDS];
static SERVED: AtomicU64 = AtomicU64::new(0);
static FALLBACKS: AtomicU64 = AtomicU64::new(0);
static IN_USE: AtomicUsize = AtomicUsize::new(0);
static PEAK_IN_USE: AtomicUsize = AtomicUsize::new(0);
static LARGEST_REQUEST: AtomicUsize = AtomicUsize::new(0);
static LOOP_SYSTEM: AtomicU64 = AtomicU64::new(0);
static LOOP_SYSTEM_FREES: AtomicU64 = AtomicU64::new(0);
static LOOP_REQUESTS: AtomicU64 = AtomicU64::new(0);

thread_local! {
    // `const`, no destructor: reading it never allocates, so the allocator may.
    static REALTIME: Cell<bool> = const { Cell::new(false) };
    static IN_LOOP: Cell<bool> = const { Cell::new(false) };
}

/// While alive, the calling thread is inside its loop (and marked real-time): its requests
/// are counted (`PoolStats::loop_requests`), and those that reach the system allocator, and
/// its frees of system blocks, apart (`loop_system_allocations`, `loop_system_frees`: 0 in
/// a loop that keeps the rule). Entered by every loop of the processes; it stays on its
/// thread (not `Send`) and restores the thread's state before it when dropped.
pub struct LoopSection {
    was_in_loop: bool,
    _on_this_thread: std::marker::PhantomData<*const ()>,
}

impl LoopSection {
    pub fn enter() -> LoopSection {
        mark_this_thread_realtime();
        LoopSection {
            was_in_loop: IN_LOOP.with(|l| l.replace(true)),
            _on_this_thread: std::marker::PhantomData,
        }
    }
}

impl Drop for LoopSection {
    fn drop(&mut self) {
        let _ = IN_LOOP.try_with(|l| l.set(self.was_in_loop));
    }
}

fn in_loop() -> bool {
    IN_LOOP.try_with(Cell::get).unwrap_or(false)
}

/// Counts a request about to reach the system allocator if the thread is in its loop.
fn count_if_in_loop() {
    if in_loop() {
        LOOP_SYSTEM.fetch_add(1, Ordering::Relaxed);
    }
}

/// Marks the calling thread real-time: its small allocations come from the pool from now on.
pub fn mark_this_thread_realtime() {
    REALTIME.with(|r| r.set(true));
}

/// Whether the calling thread is marked.
pub fn this_thread_is_realtime() -> bool {
    REALTIME.try_with(Cell::get).unwrap_or(false)
}

/// What the pool has done in this process.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub struct PoolStats {
    /// Requests on marked threads served from the pool.
    pub served: u64,
    /// Requests on marked threads (allocations and reallocations) that went to the system
    /// allocator: too large, too aligned, or the pool full.
    pub fallbacks: u64,
    /// Blocks in use now, and the most at once.
    pub in_use: usize,
    pub peak_in_use: usize,
    /// The largest request seen on a marked thread, bytes.
    pub largest_request_bytes: usize,
    /// Requests (allocations and reallocations) made inside a loop (`LoopSection`): the
    /// pool's and the system's.
    pub loop_requests: u64,
    /// Of those, the ones that reached the system allocator.
    pub loop_system_allocations: u64,
    /// Frees of system blocks inside a loop (they reach the system allocator too).
    pub loop_system_frees: u64,
}

/// The pool's counters (relaxed reads; exact once the threads that allocate are quiet).
pub fn stats() -> PoolStats {
    PoolStats {
        served: SERVED.load(Ordering::Relaxed),
        fallbacks: FALLBACKS.load(Ordering::Relaxed),
        in_use: IN_USE.load(Ordering::Relaxed),
        peak_in_use: PEAK_IN_USE.load(Ordering::Relaxed),
        largest_request_bytes: LARGEST_REQUEST.load(Ordering::Relaxed),
        loop_requests: LOOP_REQUESTS.load(Ordering::Relaxed),
        loop_system_allocations: LOOP_SYSTEM.load(Ordering::Relaxed),
        loop_system_frees: LOOP_SYSTEM_FREES.load(Ordering::Relaxed),
    }
}

fn base() -> usize {
    MEMORY.0.get() as usize
}

fn in_pool(ptr: *mut u8) -> bool {
    let p = ptr as usize;
    p >= base() && p < base() + BLOCKS * BLOCK_BYTES
}

/// Takes a free block: the first clear bit, claimed by compare-and-swap (lock-free: a
/// failed swap means another thread took or gave one, and the word is read again).
fn take() -> Option<*mut u8> {
    for (w, word) in USED.iter().enumerate() {
        let mut current = word.load(Ordering::Relaxed);
        while current != u64::MAX {
            let bit = (!current).trailing_zeros() as usize;
            match word.compare_exchange_weak(
                current,
                current | (1 << bit),
                Ordering::Acquire,
                Ordering::Relaxed,
            ) {
                Ok(_) => {
                    let now = IN_USE.fetch_add(1, Ordering::Relaxed) + 1;
                    PEAK_IN_USE.fetch_max(now, Ordering::Relaxed);
                    // SAFETY: the index is below BLOCKS; the bit makes the block ours.
                    return Some(unsafe {
                        (MEMORY.0.get() as *mut Block).add(w * 64 + bit) as *mut u8
                    });
                }
                Err(now) => current = now,
            }
        }
    }
    None
}

/// Gives a block back (from any thread). A block not in use is a double free: abort
/// rather than free whoever holds it now.
fn give(ptr: *mut u8) {
    let index = (ptr as usize - base()) / BLOCK_BYTES;
    let bit = 1u64 << (index % 64);
    if USED[index / 64].fetch_and(!bit, Ordering::Release) & bit == 0 {
        std::process::abort();
    }
    IN_USE.fetch_sub(1, Ordering::Relaxed);
}

/// A global allocator: small requests on marked threads from the pool, everything else
/// from `inner`. Use as `#[global_allocator] static A: RtPool<System> = RtPool::new(System);`.
pub struct RtPool<A> {
    inner: A,
}

impl<A> RtPool<A> {
    pub const fn new(inner: A) -> Self {
        RtPool { inner }
    }

    /// A block for `layout` if the calling thread is marked and the request fits.
    fn pooled(&self, layout: Layout) -> Option<*mut u8> {
        if !this_thread_is_realtime() {
            return None;
        }
        if in_loop() {
            LOOP_REQUESTS.fetch_add(1, Ordering::Relaxed);
        }
        LARGEST_REQUEST.fetch_max(layout.size(), Ordering::Relaxed);
        let block = if layout.size() <= BLOCK_BYTES && layout.align() <= BLOCK_BYTES {
            take()
        } else {
            None
        };
        match block {
            Some(_) => SERVED.fetch_add(1, Ordering::Relaxed),
            None => FALLBACKS.fetch_add(1, Ordering::Relaxed),
        };
        block
    }
}

// SAFETY: pool blocks are `BLOCK_BYTES` long and aligned to it, handed out only for layouts
// that fit, and owned exclusively until given back; every other request is `inner`'s.
unsafe impl<A: GlobalAlloc> GlobalAlloc for RtPool<A> {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        match self.pooled(layout) {
            Some(p) => p,
            None => {
                count_if_in_loop();
                unsafe { self.inner.alloc(layout) }
            }
        }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        match self.pooled(layout) {
            Some(p) => {
                // SAFETY: the block is ours and at least `layout.size()` long.
                unsafe { p.write_bytes(0, layout.size()) };
                p
            }
            None => {
                count_if_in_loop();
                unsafe { self.inner.alloc_zeroed(layout) }
            }
        }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        if in_pool(ptr) {
            give(ptr);
        } else {
            if in_loop() {
                LOOP_SYSTEM_FREES.fetch_add(1, Ordering::Relaxed);
            }
            unsafe { self.inner.dealloc(ptr, layout) }
        }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if !in_pool(ptr) {
            if this_thread_is_realtime() {
                FALLBACKS.fetch_add(1, Ordering::Relaxed);
                if in_loop() {
                    LOOP_REQUESTS.fetch_add(1, Ordering::Relaxed);
                }
            }
            count_if_in_loop();
            return unsafe { self.inner.realloc(ptr, layout, new_size) };
        }
        if new_size <= BLOCK_BYTES {
            return ptr;
        }
        // SAFETY: the caller guarantees `new_size` with `layout.align()` is a valid layout.
        let grown = unsafe { Layout::from_size_align_unchecked(new_size, layout.align()) };
        let p = unsafe { self.alloc(grown) };
        if !p.is_null() {
            // SAFETY: both are valid for `layout.size()` bytes and distinct.
            unsafe { std::ptr::copy_nonoverlapping(ptr, p, layout.size()) };
            give(ptr);
        }
        p
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::alloc::System;

    /// The only test touching the process's pool (the unit tests' own allocator is the
    /// system's): unmarked threads never get a block; a marked one gets distinct, aligned
    /// blocks until the pool is full, then the system's, counted; blocks come home from
    /// another thread; a block grows by moving out with its bytes.
    #[test]
    fn marked_threads_take_blocks_until_the_pool_is_full_and_any_thread_gives_them_back() {
        let pool = RtPool::new(System);
        let small = Layout::from_size_align(72, 8).unwrap();
        unsafe {
            let p = pool.alloc(small);
            assert!(!in_pool(p), "an unmarked thread is served by the system");
            pool.dealloc(p, small);
        }
        let before = stats();
        let blocks: Vec<usize> = std::thread::spawn(move || {
            mark_this_thread_realtime();
            let pool = RtPool::new(System);
            let mut taken: Vec<usize> = Vec::with_capacity(BLOCKS);
            for _ in 0..BLOCKS {
                let p = unsafe { pool.alloc(small) };
                assert!(in_pool(p) && (p as usize).is_multiple_of(BLOCK_BYTES));
                taken.push(p as usize);
            }
            // Full: the system's, counted.
            let extra = unsafe { pool.alloc(small) };
            assert!(!extra.is_null() && !in_pool(extra));
            unsafe { pool.dealloc(extra, small) };
            let big = Layout::from_size_align(BLOCK_BYTES + 1, 8).unwrap();
            let p = unsafe { pool.alloc(big) };
            assert!(!in_pool(p));
            unsafe { pool.dealloc(p, big) };
            taken
        })
        .join()
        .unwrap();
        let mut distinct = blocks.clone();
        distinct.sort_unstable();
        distinct.dedup();
        assert_eq!(distinct.len(), BLOCKS);
        let full = stats();
        assert_eq!(full.served - before.served, BLOCKS as u64);
        assert_eq!(full.fallbacks - before.fallbacks, 2);
        assert_eq!(full.in_use, BLOCKS);
        assert_eq!(full.peak_in_use, BLOCKS);
        assert!(full.largest_request_bytes > BLOCK_BYTES);
        // Given back here, on an unmarked thread.
        for &p in &blocks {
            unsafe { pool.dealloc(p as *mut u8, small) };
        }
        assert_eq!(stats().in_use, 0);
        // A block that grows past its size moves to the system with its bytes.
        std::thread::spawn(move || {
            mark_this_thread_realtime();
            let pool = RtPool::new(System);
            unsafe {
                let p = pool.alloc_zeroed(small);
                assert!(in_pool(p) && *p == 0);
                *p = 7;
                assert_eq!(pool.realloc(p, small, 100), p, "still fits");
                let q = pool.realloc(p, small, 4 * BLOCK_BYTES);
                assert!(!in_pool(q) && *q == 7);
                pool.dealloc(q, Layout::from_size_align(4 * BLOCK_BYTES, 8).unwrap());
            }
        })
        .join()
        .unwrap();
        assert_eq!(stats().in_use, 0);
        // Inside a loop section a request the pool cannot serve is counted, one it serves
        // is not; after the section, neither.
        std::thread::spawn(move || {
            let pool = RtPool::new(System);
            let big = Layout::from_size_align(4 * BLOCK_BYTES, 8).unwrap();
            let before = stats();
            {
                let _loop = LoopSection::enter();
                assert!(this_thread_is_realtime());
                {
                    // Nested: its end leaves the outer section in force.
                    let _inner = LoopSection::enter();
                }
                unsafe {
                    let p = pool.alloc(small);
                    pool.dealloc(p, small);
                    let q = pool.alloc(big);
                    pool.dealloc(q, big);
                }
            }
            unsafe {
                let q = pool.alloc(big);
                pool.dealloc(q, big);
            }
            let after = stats();
            assert_eq!(after.loop_requests - before.loop_requests, 2);
            assert_eq!(
                after.loop_system_allocations - before.loop_system_allocations,
                1
            );
            assert_eq!(after.loop_system_frees - before.loop_system_frees, 1);
        })
        .join()
        .unwrap();
    }
}
