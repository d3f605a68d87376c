//! A program's memory policy for the stages' large, short-lived tensors: glibc's heap set to
//! keep freed memory ([`keep_freed_memory`]) and an allocator that advises large blocks for huge
//! pages ([`HugePageAdvice`]). The libraries never install either; the `dsgs` binary and the
//! benchmarks do, and any program using the libraries may (`docs/performance.md`, "Keeping freed
//! memory in the process" and "Huge pages for large blocks").
//!
//! It also has the one way the libraries create their large initialised buffers (e.g. the
//! gradients of every Gaussian): [`filled`] and [`refill`], which write the elements on the
//! threads of the current rayon pool instead of the calling thread alone; and
//! [`fill_uninit`], for a buffer whose parts are initialised where they are used (the
//! rasterizer's per-intersection records, each tile's part in its own task). Also
//! [`clear_with_capacity`], to empty a reused buffer and grow it without copying its old
//! contents, and the one cache hint of the libraries, [`prefetch`].

use std::alloc::{GlobalAlloc, Layout, System};
use std::mem::MaybeUninit;

use rayon::iter::ParallelExtend;

/// Below this many bytes [`refill`] writes on the calling thread: splitting the work costs
/// more than it saves (about the size where two threads' memset beats one by a handoff).
const PARALLEL_FILL_BYTES: usize = 1 << 20;

/// A vector of `len` copies of `value`. The same vector as `vec![value; len]`; long ones are
/// written by the threads of the current rayon pool (see [`refill`]).
pub fn filled<T: Clone + Send + Sync>(len: usize, value: T) -> Vec<T> {
    let mut v = Vec::new();
    refill(&mut v, len, value);
    v
}

/// Makes `v` hold `len` copies of `value` (its old elements dropped, its allocation reused when
/// large enough). From 1 MiB on, the elements are written in parallel parts by the threads of
/// the current rayon pool: a stage that calls this from its main thread (outside the pool)
/// would otherwise clear tens of megabytes of gradients per iteration on one core while the
/// pool's threads wait (`docs/performance.md`, "Buffers filled by the pool").
pub fn refill<T: Clone + Send + Sync>(v: &mut Vec<T>, len: usize, value: T) {
    v.clear();
    if len.saturating_mul(size_of::<T>()) < PARALLEL_FILL_BYTES {
        v.resize(len, value);
    } else {
        v.par_extend(rayon::iter::repeat_n(value, len));
    }
}

/// Empties `v` and makes room for at least `capacity` elements. Unlike `clear` and then
/// `reserve`, which reallocates and so copies the whole old buffer (the allocator does not know
/// that none of it is in use), a buffer too small is dropped and a new one allocated.
pub fn clear_with_capacity<T>(v: &mut Vec<T>, capacity: usize) {
    v.clear();
    if v.capacity() < capacity {
        *v = Vec::with_capacity(capacity);
    }
}

/// Writes `value` into every element of `v`, a buffer not yet written (e.g. part of a vector's
/// spare capacity), and returns it as written. For a part that its user initialises itself, in
/// cache, instead of a whole buffer filled in advance ([`refill`]).
pub fn fill_uninit<T: Copy>(v: &mut [MaybeUninit<T>], value: T) -> &mut [T] {
    for x in v.iter_mut() {
        x.write(value);
    }
    // SAFETY: every element was written just above, and `MaybeUninit<T>` has the layout of `T`.
    unsafe { &mut *(std::ptr::from_mut(v) as *mut [T]) }
}

/// Asks the processor to bring the cache lines of `data` closer (a hint: no effect on any
/// result). Loops that visit Gaussians scattered over memory (a tile list in depth order, the
/// records of one Gaussian) prefetch a few ahead to overlap those accesses with their work, and
/// loops that stream long per-Gaussian rows prefetch a block ahead.
#[inline(always)]
pub fn prefetch<T>(data: &[T]) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        let start = data.as_ptr() as *const i8;
        let end = start.wrapping_add(std::mem::size_of_val(data));
        let mut line = start;
        while line < end {
            // SAFETY: a prefetch never faults and changes no architectural state; the address
            // lies inside `data`.
            unsafe { _mm_prefetch::<_MM_HINT_T0>(line) };
            line = line.wrapping_add(64);
        }
        // The last line, when `data` ends past a multiple of 64 bytes from its start.
        if end > start {
            // SAFETY: as above.
            unsafe { _mm_prefetch::<_MM_HINT_T0>(end.wrapping_sub(1)) };
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = data;
}

/// Asks glibc's allocator to serve allocations below 1 GiB from its heap and to keep up to
/// 2 GiB of freed memory there instead of returning it to the system. The stages allocate and
/// free tensors of tens of megabytes many times per iteration (a 256-channel 256x256 activation
/// is 64 MiB); by default each is mapped afresh, and the kernel faults in and clears every page
/// again. Measured on a 256->256 convolution at 256x256: 1.15x to 1.35x faster with this
/// setting, and the munmap calls of a benchmark run fell from 79 to 6 (`docs/performance.md`).
/// The cost is that the process keeps its peak heap until it exits. It also puts every thread
/// on the one heap (glibc's `M_ARENA_MAX` of 1), so that blocks freed on rayon's threads are
/// kept too. Call it at start-up, before the large allocations and the threads; elsewhere than
/// with glibc it does nothing.
pub fn keep_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only changes allocator parameters (under glibc's own lock), and a value
    // it rejects leaves the default in place.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 1 << 30);
        libc::mallopt(libc::M_TRIM_THRESHOLD, i32::MAX);
        // One arena for every thread: a rayon pool thread's own arena cannot keep blocks
        // above 64 MiB (glibc's heap size for threads), so it would map and unmap them at
        // every call, whatever the threshold above.
        libc::mallopt(libc::M_ARENA_MAX, 1);
    }
}

/// The system allocator, with every block of at least 4 MiB advised for
/// transparent huge pages (`madvise(MADV_HUGEPAGE)` on the 2 MiB pages it covers whole), so that
/// the kernel maps fresh memory there 2 MiB at a time where it allows huge pages on request
/// (the `madvise` mode of `/sys/kernel/mm/transparent_hugepage/enabled`, a common default).
/// A block is what the system allocator returns, unchanged; the advice only changes how its
/// pages are mapped, never their contents, and a refused advice is ignored. Blocks that are
/// already mapped (memory the heap reuses) keep their pages. Elsewhere than on Linux this is
/// the system allocator.
pub struct HugePageAdvice;

/// The smallest block advised: two huge pages, so that every block advised covers at least one
/// whole huge page, and the small allocations (the vast majority) cost nothing more.
const ADVISE_FROM: usize = 4 << 20;

/// `ptr`, a block of `len` bytes from the system allocator, advised when it is large enough.
#[inline]
fn advised(ptr: *mut u8, len: usize) -> *mut u8 {
    if len >= ADVISE_FROM {
        advise(ptr, len);
    }
    ptr
}

/// Advises the whole 2 MiB pages of the `len` bytes at `ptr` (a block from the allocator).
#[inline]
fn advise(ptr: *mut u8, len: usize) {
    #[cfg(target_os = "linux")]
    {
        const HUGE_PAGE: usize = 2 << 20;
        let start = (ptr as usize).next_multiple_of(HUGE_PAGE);
        let end = (ptr as usize + len) / HUGE_PAGE * HUGE_PAGE;
        if !ptr.is_null() && end > start {
            // SAFETY: the range lies inside a block the allocator has just handed out, which
            // is mapped, readable and writable; MADV_HUGEPAGE changes neither its contents nor
            // its protection. A failure (no THP support) leaves the mapping as it was.
            unsafe {
                libc::madvise(start as *mut libc::c_void, end - start, libc::MADV_HUGEPAGE);
            }
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = (ptr, len);
}

// SAFETY: every method returns what `System` returns for the same arguments; `advise` never
// changes a block's contents, size or alignment.
unsafe impl GlobalAlloc for HugePageAdvice {
    #[inline]
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // SAFETY: the caller's contract for `layout` is passed on unchanged.
        advised(unsafe { System.alloc(layout) }, layout.size())
    }

    #[inline]
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        // SAFETY: as `alloc`. The system allocator's own zeroing is kept: it skips memory fresh
        // from the kernel (zero already), which is then faulted in only when first written.
        advised(unsafe { System.alloc_zeroed(layout) }, layout.size())
    }

    #[inline]
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: `ptr` came from `System` with `layout`, as the caller guarantees.
        unsafe { System.dealloc(ptr, layout) }
    }

    #[inline]
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // SAFETY: the caller's contract for `ptr`, `layout` and `new_size` is passed on.
        advised(unsafe { System.realloc(ptr, layout, new_size) }, new_size)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `filled` and `refill` give `vec![value; len]` on both sides of the parallel size, for
    /// elements of several sizes, and `refill` replaces what the vector held, growing or
    /// shrinking.
    #[test]
    fn filled_vectors_equal_the_serial_ones() {
        let big = PARALLEL_FILL_BYTES / 4;
        for len in [0, 1, 17, big - 1, big, 3 * big + 5] {
            assert_eq!(filled(len, 1.5f32), vec![1.5f32; len]);
            assert_eq!(filled(len, [0u32, 7]), vec![[0u32, 7]; len]);
        }
        let mut v = vec![9.0f64; 10];
        for len in [4 * big, 3, big / 2 + 1, 0, big + 11] {
            refill(&mut v, len, -2.0);
            assert_eq!(v, vec![-2.0; len], "refill to {len}");
        }
    }

    /// `clear_with_capacity` leaves an empty vector with room for what was asked, keeping a
    /// buffer that is large enough.
    #[test]
    fn cleared_vectors_have_the_capacity_asked_for() {
        let mut v: Vec<u64> = (0..10).collect();
        let kept = v.as_ptr();
        clear_with_capacity(&mut v, 4);
        assert!(v.is_empty() && v.capacity() >= 10 && v.as_ptr() == kept);
        v.extend(0..3);
        clear_with_capacity(&mut v, 1000);
        assert!(v.is_empty() && v.capacity() >= 1000);
    }

    /// `fill_uninit` writes every element of the part it is given and no other: a vector's
    /// spare capacity filled in two parts with different values reads back as those values.
    #[test]
    fn uninitialised_parts_fill_with_their_value() {
        for (len, cut) in [(0, 0), (1, 0), (1, 1), (37, 5), (1000, 999)] {
            let mut v: Vec<u32> = Vec::with_capacity(len);
            let (head, tail) = v.spare_capacity_mut()[..len].split_at_mut(cut);
            assert_eq!(fill_uninit(head, 7), vec![7; cut]);
            assert_eq!(fill_uninit(tail, 9), vec![9; len - cut]);
            // SAFETY: the first `len` elements were written by the two calls above.
            unsafe { v.set_len(len) };
            let want: Vec<u32> = (0..len).map(|i| if i < cut { 7 } else { 9 }).collect();
            assert_eq!(v, want);
        }
    }

    /// The advised allocator hands out blocks that hold what is written to them, zeroed ones
    /// zero, and keeps a reallocated block's contents, on both sides of the advised size.
    #[test]
    fn blocks_keep_their_contents_and_zeroed_blocks_are_zero() {
        let a = HugePageAdvice;
        for size in [64, ADVISE_FROM - 8, ADVISE_FROM, 3 * ADVISE_FROM + 12_345] {
            let layout = Layout::from_size_align(size, 64).expect("valid layout");
            // SAFETY: non-zero sizes, valid layouts; each block is freed once with its layout.
            unsafe {
                let z = a.alloc_zeroed(layout);
                assert!(!z.is_null());
                let zs = std::slice::from_raw_parts(z, size);
                assert!(zs.iter().all(|&b| b == 0), "zeroed block of {size} bytes");
                a.dealloc(z, layout);

                let p = a.alloc(layout);
                assert!(!p.is_null());
                assert_eq!(p as usize % 64, 0, "alignment kept");
                for i in 0..size {
                    *p.add(i) = (i % 251) as u8;
                }
                let grown = 2 * size + 7;
                let q = a.realloc(p, layout, grown);
                assert!(!q.is_null());
                let qs = std::slice::from_raw_parts(q, size);
                assert!(qs.iter().enumerate().all(|(i, &b)| b == (i % 251) as u8));
                a.dealloc(q, Layout::from_size_align(grown, 64).expect("valid layout"));
            }
        }
    }
}
