//! A 64-byte aligned, zero-initialised buffer for packed operands, so that
//! every kernel load of a packed panel stays within one cache line.

use std::alloc::{alloc_zeroed, dealloc, Layout};

/// Smallest long-lived buffer given its own mapping: smaller ones fit the
/// heap's holes anyway, and a mapping costs a system call and whole pages.
const MAPPED_MIN_BYTES: usize = 1 << 20;

/// A 64-byte aligned, zero-initialised buffer of `T` (large long-lived ones get their own mapping).
pub struct AlignedBuf<T: Copy> {
    ptr: *mut T,
    len: usize,
    /// Bytes of this buffer's own anonymous mapping (0: from the allocator).
    mapped: usize,
}

// SAFETY: the buffer owns its allocation exclusively, like a Vec<T>.
unsafe impl<T: Copy + Send> Send for AlignedBuf<T> {}
unsafe impl<T: Copy + Sync> Sync for AlignedBuf<T> {}

impl<T: Copy> AlignedBuf<T> {
    const ALIGN: usize = 64;

    fn layout(len: usize) -> Layout {
        Layout::from_size_align(len.max(1) * std::mem::size_of::<T>(), Self::ALIGN).expect("buffer size overflows")
    }

    /// `len` elements, all bits zero (0.0 for floats).
    pub fn zeroed(len: usize) -> Self {
        let layout = Self::layout(len);
        // SAFETY: layout has non-zero size; T is Copy (plain data) so all-zero bits are a valid value
        // for the float and integer types used here.
        let ptr = unsafe { alloc_zeroed(layout) } as *mut T;
        if ptr.is_null() {
            std::alloc::handle_alloc_error(layout);
        }
        Self { ptr, len, mapped: 0 }
    }

    /// [`Self::zeroed`] for a buffer that lives as long as a model (packed
    /// weights). On Linux a large one gets its own anonymous mapping rather
    /// than heap memory: the heap then holds only short-lived buffers, so
    /// freed ones are reused without leaving holes between weights that
    /// raise peak resident memory. Elsewhere, or if the mapping fails, it is
    /// [`Self::zeroed`].
    pub fn zeroed_long_lived(len: usize) -> Self {
        #[cfg(target_os = "linux")]
        {
            let bytes = Self::layout(len).size();
            if bytes >= MAPPED_MIN_BYTES {
                // SAFETY: a fresh private anonymous mapping (zero-filled by the
                // kernel, page-aligned so 64-byte aligned); checked for failure.
                let p = unsafe {
                    libc::mmap(
                        std::ptr::null_mut(),
                        bytes,
                        libc::PROT_READ | libc::PROT_WRITE,
                        libc::MAP_PRIVATE | libc::MAP_ANONYMOUS,
                        -1,
                        0,
                    )
                };
                if p != libc::MAP_FAILED {
                    return Self { ptr: p as *mut T, len, mapped: bytes };
                }
            }
        }
        Self::zeroed(len)
    }

    /// Whether the buffer has its own mapping ([`Self::zeroed_long_lived`]).
    pub fn is_mapped(&self) -> bool {
        self.mapped > 0
    }

    /// Number of elements.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether the buffer holds no elements.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Grow (never shrink) to at least `len` elements; contents are not kept.
    pub fn ensure(&mut self, len: usize) {
        if len > self.len {
            *self = Self::zeroed(len);
        }
    }

    /// Pointer to the first element (64-byte aligned).
    pub fn as_ptr(&self) -> *const T {
        self.ptr
    }

    /// Mutable pointer to the first element (64-byte aligned).
    pub fn as_mut_ptr(&mut self) -> *mut T {
        self.ptr
    }
}

impl<T: Copy> std::ops::Deref for AlignedBuf<T> {
    type Target = [T];
    fn deref(&self) -> &[T] {
        // SAFETY: ptr is valid for len initialised elements.
        unsafe { std::slice::from_raw_parts(self.ptr, self.len) }
    }
}

impl<T: Copy> std::ops::DerefMut for AlignedBuf<T> {
    fn deref_mut(&mut self) -> &mut [T] {
        // SAFETY: as above, and we hold &mut self.
        unsafe { std::slice::from_raw_parts_mut(self.ptr, self.len) }
    }
}

impl<T: Copy> Drop for AlignedBuf<T> {
    fn drop(&mut self) {
        #[cfg(target_os = "linux")]
        if self.mapped > 0 {
            // SAFETY: the whole mapping made in `zeroed_long_lived`, unmapped once.
            unsafe { libc::munmap(self.ptr as *mut libc::c_void, self.mapped) };
            return;
        }
        // SAFETY: allocated in `zeroed` with the same layout.
        unsafe { dealloc(self.ptr as *mut u8, Self::layout(self.len)) }
    }
}

impl<T: Copy> Clone for AlignedBuf<T> {
    fn clone(&self) -> Self {
        let mut b = if self.is_mapped() { Self::zeroed_long_lived(self.len) } else { Self::zeroed(self.len) };
        b.copy_from_slice(self);
        b
    }
}

impl<T: Copy> std::fmt::Debug for AlignedBuf<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "AlignedBuf({} × {})", self.len, std::any::type_name::<T>())
    }
}

/// Address of a buffer shared by parallel jobs that each write a disjoint
/// part of it (output rows, panels, tiles); the writers' SAFETY comments say
/// which part is theirs.
pub(crate) struct SendPtr<T>(pub *mut T);

impl<T> Clone for SendPtr<T> {
    fn clone(&self) -> Self {
        *self
    }
}
impl<T> Copy for SendPtr<T> {}
// SAFETY: only hands disjoint regions of one buffer to worker threads.
unsafe impl<T> Send for SendPtr<T> {}
unsafe impl<T> Sync for SendPtr<T> {}

impl<T> SendPtr<T> {
    // A method (not field access) so closures capture the whole Send wrapper.
    pub fn get(self) -> *mut T {
        self.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn long_lived_buffers_are_zeroed_aligned_and_cloned() {
        for len in [0usize, 3, 1000, (MAPPED_MIN_BYTES / 4) + 5] {
            let mut b = AlignedBuf::<f32>::zeroed_long_lived(len);
            assert_eq!(b.len(), len);
            assert_eq!(b.as_ptr() as usize % 64, 0, "64-byte aligned");
            assert!(b.iter().all(|&v| v == 0.0), "zeroed");
            // Large ones have their own mapping on Linux; small ones come from the heap.
            assert_eq!(b.is_mapped(), cfg!(target_os = "linux") && len * 4 >= MAPPED_MIN_BYTES, "len {len}");
            b.iter_mut().enumerate().for_each(|(i, v)| *v = i as f32);
            let c = b.clone();
            assert_eq!(c.is_mapped(), b.is_mapped());
            assert!(c.iter().enumerate().all(|(i, &v)| v == i as f32));
        }
    }
}
