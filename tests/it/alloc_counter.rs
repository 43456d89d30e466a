//! A counting global allocator for the test binary, over the processes' own allocator
//! (`fastemu::rt::pool::RtPool`): it counts the requests, and those that reach the system.
//!
//! Tests run in parallel threads, so counting is per thread: only allocations made by the
//! calling thread while it is inside `count_allocations` are counted. Other tests'
//! allocations on other threads never leak into the count.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

use fastemu::rt::pool::RtPool;

struct CountingAllocator;

/// The system allocator, counting the calls that reach it.
struct CountingSystem;

thread_local! {
    // `const` initialisers without destructors: touching them never allocates, so they
    // are safe to use from inside the allocator.
    static COUNTING: Cell<bool> = const { Cell::new(false) };
    static ALLOCATIONS: Cell<usize> = const { Cell::new(0) };
    static SYSTEM_ALLOCATIONS: Cell<usize> = const { Cell::new(0) };
}

fn record(counter: &'static std::thread::LocalKey<Cell<usize>>) {
    // `try_with` because the allocator can run while a thread's locals are torn down.
    let counting = COUNTING.try_with(Cell::get).unwrap_or(false);
    if counting {
        let _ = counter.try_with(|n| n.set(n.get() + 1));
    }
}

unsafe impl GlobalAlloc for CountingSystem {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        record(&SYSTEM_ALLOCATIONS);
        unsafe { System.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        record(&SYSTEM_ALLOCATIONS);
        unsafe { System.alloc_zeroed(layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        record(&SYSTEM_ALLOCATIONS);
        unsafe { System.realloc(ptr, layout, new_size) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
}

static POOL: RtPool<CountingSystem> = RtPool::new(CountingSystem);

unsafe impl GlobalAlloc for CountingAllocator {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        record(&ALLOCATIONS);
        unsafe { POOL.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        record(&ALLOCATIONS);
        unsafe { POOL.alloc_zeroed(layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        record(&ALLOCATIONS);
        unsafe { POOL.realloc(ptr, layout, new_size) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { POOL.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static GLOBAL: CountingAllocator = CountingAllocator;

/// Runs `f` on the calling thread and returns how many allocations (`alloc`,
/// `alloc_zeroed`, `realloc`) it made. Nested calls are not supported.
pub fn count_allocations(f: impl FnOnce()) -> usize {
    count_allocations_and_system(f).0
}

/// `count_allocations`, and how many of them reached the system allocator (the others
/// came from the real-time pool: only on a thread marked real-time).
pub fn count_allocations_and_system(f: impl FnOnce()) -> (usize, usize) {
    ALLOCATIONS.with(|n| n.set(0));
    SYSTEM_ALLOCATIONS.with(|n| n.set(0));
    COUNTING.with(|c| c.set(true));
    f();
    COUNTING.with(|c| c.set(false));
    (
        ALLOCATIONS.with(Cell::get),
        SYSTEM_ALLOCATIONS.with(Cell::get),
    )
}

#[test]
fn counter_sees_allocations_made_inside_the_window() {
    // Guards against a vacuous zero-allocation test: a Vec push must be counted.
    let count = count_allocations(|| {
        let v: Vec<u64> = std::hint::black_box(Vec::with_capacity(16));
        drop(v);
    });
    assert_eq!(count, 1);
    assert_eq!(count_allocations(|| {}), 0);
    // Not marked real-time: it reached the system allocator.
    let both = count_allocations_and_system(|| drop(std::hint::black_box(vec![1u8; 16])));
    assert_eq!(both, (1, 1));
}
