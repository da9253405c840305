//! A 64-byte aligned, zero-initialised buffer for packed operands, so that
//! every kernel load of a packed panel stays within one cache line.

use std::alloc::{alloc_zeroed, dealloc, Layout};

pub struct AlignedBuf<T: Copy> {
    ptr: *mut T,
    len: usize,
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
        Self { ptr, len }
    }

    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Grow (never shrink) to at least `len` elements; contents are not kept.
    pub fn ensure(&mut self, len: usize) {
        if len > self.len {
            *self = Self::zeroed(len);
        }
    }

    pub fn as_ptr(&self) -> *const T {
        self.ptr
    }

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
        // SAFETY: allocated in `zeroed` with the same layout.
        unsafe { dealloc(self.ptr as *mut u8, Self::layout(self.len)) }
    }
}

impl<T: Copy> Clone for AlignedBuf<T> {
    fn clone(&self) -> Self {
        let mut b = Self::zeroed(self.len);
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
