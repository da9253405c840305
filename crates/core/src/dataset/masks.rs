//! Object masks: an instance-id PNG (0 = background, one id per object; 8-
//! or 16-bit) or one binary mask file per object, object selection by id,
//! RecGen's mask erosion, and per-object validation against the frame.
//!
//! Validation never fails the whole frame: each object either passes or is
//! reported as a [`MaskSkip`] with the reason (absent id, empty mask, size
//! different from the frame, nothing left after erosion, too few pixels
//! with a valid depth reading under the eroded mask), so the caller can go
//! on with the others.
//!
//! **Erosion (RecGen `apply_mask_erosion`).** Before anything else RecGen
//! erodes the object mask with a `k×k` square of ones (`k = 5`, 1 iteration
//! by default) as `scipy.ndimage.binary_erosion` does: a pixel stays set
//! only if every pixel of the window centred on it (offsets `-k/2 ..
//! k-1-k/2`) is set, and pixels outside the image count as unset, so a mask
//! touching the border loses its border rows. This trims the mixed
//! object/background depth at silhouettes. The eroded mask is what the
//! crop, the point statistics and the mask tensor all use.

use std::path::{Path, PathBuf};

use crate::dataset::frame::{depth_valid, RgbdFrame};
use crate::{Error, Result};

/// A run of object pixels on one row: `len` pixels from `(x, y)` rightwards.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Run {
    /// Row.
    pub y: u32,
    /// First column.
    pub x: u32,
    /// Pixels in the run (at least 1).
    pub len: u32,
}

/// One object's mask in a frame, held sparsely as row runs: a frame of many
/// small instances costs memory by its object pixels, not by frame size ×
/// instance count. The full-frame form ([`ObjectMask::to_bools`]) is made
/// only for an object that passes [`validate_objects`], when it is prepared.
#[derive(Debug, Clone, PartialEq)]
pub struct ObjectMask {
    /// Instance id in the label map (`None` for a mask file).
    pub id: Option<u32>,
    /// Human-readable name for reports (`id 8`, or the file name).
    pub label: String,
    /// Width of the frame the mask belongs to, pixels.
    pub width: usize,
    /// Height of the frame the mask belongs to, pixels.
    pub height: usize,
    /// The object's pixels: runs ordered by row then column, neither
    /// overlapping nor touching on a row.
    runs: Vec<Run>,
}

impl ObjectMask {
    /// From a full-frame mask, row-major `height·width`, `true` = object.
    ///
    /// # Panics
    /// When `mask.len() != width·height`, or a side exceeds `u32::MAX`.
    pub fn from_bools(id: Option<u32>, label: impl Into<String>, width: usize, height: usize, mask: &[bool]) -> Self {
        assert_eq!(mask.len(), width * height, "mask of {} values for a {width}×{height} frame", mask.len());
        let mut runs = Vec::new();
        if width > 0 {
            for (y, row) in mask.chunks_exact(width).enumerate() {
                push_row_runs(&mut runs, y, row.iter().copied());
            }
        }
        ObjectMask { id, label: label.into(), width, height, runs }
    }

    /// From runs already ordered by row then column and not overlapping (adjacent
    /// runs on a row are merged).
    ///
    /// # Panics
    /// When the runs are out of order, overlap, or leave the `width×height` frame.
    pub fn from_runs(id: Option<u32>, label: impl Into<String>, width: usize, height: usize, runs: Vec<Run>) -> Self {
        let mut merged: Vec<Run> = Vec::with_capacity(runs.len());
        for r in runs {
            assert!(r.len > 0 && r.x as usize + r.len as usize <= width && (r.y as usize) < height, "run {r:?} outside {width}×{height}");
            if let Some(p) = merged.last_mut() {
                assert!(r.y > p.y || (r.y == p.y && r.x >= p.x + p.len), "runs out of order: {p:?} then {r:?}");
                if p.y == r.y && p.x + p.len == r.x {
                    p.len += r.len;
                    continue;
                }
            }
            merged.push(r);
        }
        ObjectMask { id, label: label.into(), width, height, runs: merged }
    }

    /// The object's row runs (ordered by row then column).
    pub fn runs(&self) -> &[Run] {
        &self.runs
    }

    /// Number of object pixels.
    pub fn pixel_count(&self) -> usize {
        self.runs.iter().map(|r| r.len as usize).sum()
    }

    /// The full-frame form: row-major `height·width`, `true` = object.
    pub fn to_bools(&self) -> Vec<bool> {
        let mut m = vec![false; self.width * self.height];
        for r in &self.runs {
            let i = r.y as usize * self.width + r.x as usize;
            m[i..i + r.len as usize].fill(true);
        }
        m
    }

    /// 8-bit 0/255 full-frame copy (the form RecGen hands to PIL).
    pub fn to_u8(&self) -> Vec<u8> {
        self.to_bools().into_iter().map(|m| if m { 255 } else { 0 }).collect()
    }
}

/// Appends the runs of `true` in row `y` (values left to right).
fn push_row_runs(runs: &mut Vec<Run>, y: usize, row: impl Iterator<Item = bool>) {
    let mut start: Option<usize> = None;
    let mut x = 0usize;
    for b in row {
        match (b, start) {
            (true, None) => start = Some(x),
            (false, Some(s)) => {
                runs.push(Run { y: y as u32, x: s as u32, len: (x - s) as u32 });
                start = None;
            }
            _ => {}
        }
        x += 1;
    }
    if let Some(s) = start {
        runs.push(Run { y: y as u32, x: s as u32, len: (x - s) as u32 });
    }
}

/// Square binary erosion parameters (RecGen defaults: 5, 1).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Erosion {
    /// Side of the square structuring element, pixels.
    pub kernel: usize,
    /// Number of erosion passes.
    pub iterations: usize,
}

impl Default for Erosion {
    fn default() -> Self {
        Erosion { kernel: 5, iterations: 1 }
    }
}

/// Binary erosion with a `k×k` square, scipy conventions (module docs).
/// Separable: a row-wise window minimum followed by a column-wise one.
pub fn erode(mask: &[bool], w: usize, h: usize, e: Erosion) -> Vec<bool> {
    let mut cur = mask.to_vec();
    if e.kernel <= 1 || e.iterations == 0 {
        return cur;
    }
    let lo = (e.kernel / 2) as isize; // window covers [i - lo, i - lo + k - 1]
    let k = e.kernel as isize;
    let win_all = |line: &[bool]| -> Vec<bool> {
        // Prefix counts of unset pixels; outside the line counts as unset.
        let n = line.len() as isize;
        let mut pre = vec![0usize; line.len() + 1];
        for (i, &b) in line.iter().enumerate() {
            pre[i + 1] = pre[i] + (!b) as usize;
        }
        (0..n)
            .map(|i| {
                let (a, b) = (i - lo, i - lo + k - 1);
                if a < 0 || b >= n {
                    return false;
                }
                pre[(b + 1) as usize] - pre[a as usize] == 0
            })
            .collect()
    };
    for _ in 0..e.iterations {
        let mut rows = vec![false; w * h];
        for y in 0..h {
            rows[y * w..(y + 1) * w].copy_from_slice(&win_all(&cur[y * w..(y + 1) * w]));
        }
        let mut col = vec![false; h];
        for x in 0..w {
            for y in 0..h {
                col[y] = rows[y * w + x];
            }
            for (y, v) in win_all(&col).into_iter().enumerate() {
                cur[y * w + x] = v;
            }
        }
    }
    cur
}

/// [`erode`] on row runs ([`ObjectMask::runs`]): the same pixels, at a cost
/// proportional to the runs instead of the frame (a one-pixel instance costs
/// next to nothing). Rows first, then columns, as [`erode`].
pub fn erode_runs(runs: &[Run], h: usize, e: Erosion) -> Vec<Run> {
    let mut cur = runs.to_vec();
    if e.kernel <= 1 || e.iterations == 0 {
        return cur;
    }
    let Ok(k) = u32::try_from(e.kernel) else {
        return Vec::new();
    };
    let (lo, hi) = (k / 2, k - 1 - k / 2); // window [i - lo, i + hi]
    for _ in 0..e.iterations {
        // Along a row, a pixel stays when its window lies in its run (the run is in the image).
        let rows: Vec<Run> = cur.iter().filter(|r| r.len >= k).map(|r| Run { y: r.y, x: r.x + lo, len: r.len - (k - 1) }).collect();
        // Along a column, row y keeps what every row y - lo ..= y + hi keeps; rows outside
        // the image keep nothing. A kept pixel is in its own row, so only rows with runs are tried.
        let row_of = |y: u32| -> &[Run] {
            let a = rows.partition_point(|r| r.y < y);
            let b = a + rows[a..].partition_point(|r| r.y == y);
            &rows[a..b]
        };
        let mut next = Vec::new();
        let mut i = 0;
        while i < rows.len() {
            let y = rows[i].y;
            let own = row_of(y);
            i += own.len();
            if y < lo || y as usize + hi as usize >= h {
                continue;
            }
            let mut acc: Vec<Run> = own.to_vec();
            for yy in (y - lo..=y + hi).filter(|&yy| yy != y) {
                if acc.is_empty() {
                    break;
                }
                acc = intersect_row(&acc, row_of(yy), y);
            }
            next.extend(acc);
        }
        cur = next;
    }
    cur
}

/// The pixels of row `y` in both `a` and `b` (runs of one row each, ordered), as runs on row `y`.
fn intersect_row(a: &[Run], b: &[Run], y: u32) -> Vec<Run> {
    let (mut i, mut j, mut out) = (0, 0, Vec::new());
    while i < a.len() && j < b.len() {
        let (ea, eb) = (a[i].x + a[i].len, b[j].x + b[j].len);
        let s = a[i].x.max(b[j].x);
        let end = ea.min(eb);
        if s < end {
            out.push(Run { y, x: s, len: end - s });
        }
        if ea < eb {
            i += 1;
        } else {
            j += 1;
        }
    }
    out
}

/// A per-instance label map (0 = background).
#[derive(Debug, Clone)]
pub struct InstanceMap {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// Instance id per pixel, row-major (0 = background).
    pub ids: Vec<u32>,
    /// The file it was read from.
    pub path: PathBuf,
}

impl InstanceMap {
    /// Read an 8- or 16-bit single-channel PNG of instance ids.
    pub fn open(path: &Path) -> Result<Self> {
        let file = path.display().to_string();
        let img = crate::util::open_image(path, "instance mask")?;
        let (w, h) = (img.width() as usize, img.height() as usize);
        let ids: Vec<u32> = match img {
            image::DynamicImage::ImageLuma8(b) => b.into_raw().into_iter().map(u32::from).collect(),
            image::DynamicImage::ImageLuma16(b) => b.into_raw().into_iter().map(u32::from).collect(),
            other => {
                return Err(Error::input(
                    &file,
                    format!("an instance-id mask must be a single-channel 8- or 16-bit PNG, found {:?}", other.color()),
                ))
            }
        };
        Ok(InstanceMap { width: w, height: h, ids, path: path.to_path_buf() })
    }

    /// Non-zero ids present, ascending.
    pub fn present_ids(&self) -> Vec<u32> {
        let mut v: Vec<u32> = self.ids.iter().copied().filter(|&i| i != 0).collect();
        v.sort_unstable();
        v.dedup();
        v
    }

    /// Masks for the selected ids (all present ids when `select` is `None`).
    /// Requested ids that do not occur are reported as skips.
    ///
    /// One pass over the map collects every instance's row runs; no
    /// full-frame buffer is made per instance, so 20 000 instances cost
    /// their pixels, not 20 000 frames.
    pub fn objects(&self, select: Option<&[u32]>) -> (Vec<ObjectMask>, Vec<MaskSkip>) {
        let mut runs: Vec<(u32, Run)> = Vec::new();
        if self.width > 0 {
            for (y, row) in self.ids.chunks_exact(self.width).enumerate() {
                let mut x = 0;
                while x < row.len() {
                    let (id, s) = (row[x], x);
                    while x < row.len() && row[x] == id {
                        x += 1;
                    }
                    if id != 0 {
                        runs.push((id, Run { y: y as u32, x: s as u32, len: (x - s) as u32 }));
                    }
                }
            }
        }
        // Stable: each id's runs stay in row order.
        runs.sort_by_key(|&(id, _)| id);
        let ids = match select {
            Some(s) => s.to_vec(),
            None => {
                let mut v: Vec<u32> = runs.iter().map(|&(id, _)| id).collect();
                v.dedup();
                v
            }
        };
        let mut out = Vec::new();
        let mut skips = Vec::new();
        for id in ids {
            let label = format!("id {id}");
            if id == 0 {
                skips.push(MaskSkip { label, reason: SkipReason::Background });
                continue;
            }
            let a = runs.partition_point(|&(i, _)| i < id);
            let b = a + runs[a..].partition_point(|&(i, _)| i == id);
            if a == b {
                skips.push(MaskSkip { label, reason: SkipReason::IdAbsent });
                continue;
            }
            let mine = runs[a..b].iter().map(|&(_, r)| r).collect();
            out.push(ObjectMask::from_runs(Some(id), label, self.width, self.height, mine));
        }
        (out, skips)
    }
}

/// Read one binary mask file: with an alpha channel that is not fully
/// opaque, `alpha > 0` marks the object; otherwise any non-zero grey value
/// does (RecGen: "non-zero pixels mark the object").
pub fn load_binary_mask(path: &Path) -> Result<ObjectMask> {
    let file = path.display().to_string();
    let img = crate::util::open_image(path, "mask")?;
    let (w, h) = (img.width() as usize, img.height() as usize);
    let mask: Vec<bool> = if img.color().has_alpha() {
        let a: Vec<u16> = img.to_luma_alpha16().pixels().map(|p| p.0[1]).collect();
        if a.iter().any(|&v| v != u16::MAX) {
            a.iter().map(|&v| v > 0).collect()
        } else {
            img.to_luma16().into_raw().into_iter().map(|v| v > 0).collect()
        }
    } else {
        img.to_luma16().into_raw().into_iter().map(|v| v > 0).collect()
    };
    let label = path.file_name().map(|s| s.to_string_lossy().into_owned()).unwrap_or(file);
    Ok(ObjectMask::from_bools(None, label, w, h, &mask))
}

/// Read several binary mask files, one object each; a file that cannot be
/// read becomes a skip for that object only.
pub fn load_binary_masks(paths: &[PathBuf]) -> (Vec<ObjectMask>, Vec<MaskSkip>) {
    let mut ok = Vec::new();
    let mut skips = Vec::new();
    for p in paths {
        match load_binary_mask(p) {
            Ok(m) => ok.push(m),
            Err(e) => skips.push(MaskSkip { label: p.display().to_string(), reason: SkipReason::Unreadable(e.to_string()) }),
        }
    }
    (ok, skips)
}

/// The masks of a frame as `recon infer --masks` takes them: one file is an
/// instance-id map (a binary 0/255 mask is the one-object case), several files are
/// binary masks, one object each. `ids` selects instance ids of a map.
pub fn load_masks(files: &[PathBuf], ids: Option<&[u32]>) -> Result<(Vec<ObjectMask>, Vec<MaskSkip>)> {
    match files {
        [] => Err(Error::input("--masks", "no mask file given")),
        [one] => Ok(InstanceMap::open(one)?.objects(ids)),
        _ if ids.is_some() => Err(Error::input(
            "--objects",
            "selects ids of an instance-id map; with several binary mask files, list only the masks you want",
        )),
        _ => Ok(load_binary_masks(files)),
    }
}

/// Why an object is left out.
#[derive(Debug, Clone, PartialEq)]
pub enum SkipReason {
    /// Id 0 is the background.
    Background,
    /// The requested id does not occur in the label map.
    IdAbsent,
    /// No pixel is set.
    Empty,
    /// The mask's size differs from the frame's.
    WrongSize {
        /// The mask's (width, height).
        mask: (usize, usize),
        /// The frame's (width, height).
        frame: (usize, usize),
    },
    /// Erosion removed every pixel (object thinner than the kernel).
    EmptyAfterErosion {
        /// Mask pixels before erosion.
        before: usize,
    },
    /// Too few pixels under the eroded mask have a valid depth reading.
    TooFewValidDepth {
        /// Eroded-mask pixels with valid depth.
        valid: usize,
        /// The minimum required.
        min: usize,
    },
    /// Point-map preprocessing failed (message).
    Preprocessing(String),
    /// The mask file could not be read (message).
    Unreadable(String),
}

impl std::fmt::Display for SkipReason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SkipReason::Background => write!(f, "id 0 is the background"),
            SkipReason::IdAbsent => write!(f, "id not present in the mask"),
            SkipReason::Empty => write!(f, "mask is empty"),
            SkipReason::WrongSize { mask, frame } => {
                write!(f, "mask is {}×{} but the frame is {}×{}", mask.0, mask.1, frame.0, frame.1)
            }
            SkipReason::EmptyAfterErosion { before } => write!(f, "mask of {before} px is empty after erosion"),
            SkipReason::TooFewValidDepth { valid, min } => {
                write!(f, "only {valid} mask pixels have valid depth (minimum {min})")
            }
            SkipReason::Preprocessing(m) => write!(f, "preprocessing failed: {m}"),
            SkipReason::Unreadable(m) => write!(f, "cannot read the mask: {m}"),
        }
    }
}

#[derive(Debug, Clone, PartialEq)]
/// An object left out of reconstruction, and why.
pub struct MaskSkip {
    /// The object's label (as in [`ObjectMask::label`]).
    pub label: String,
    /// Why it was left out.
    pub reason: SkipReason,
}

impl std::fmt::Display for MaskSkip {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}: skipped: {}", self.label, self.reason)
    }
}

/// Validation settings.
#[derive(Debug, Clone, Copy)]
pub struct MaskOptions {
    /// `None` disables erosion (RecGen `mask_erosion_enabled = False`).
    pub erosion: Option<Erosion>,
    /// Minimum number of eroded-mask pixels with valid depth.
    pub min_valid_depth_pixels: usize,
}

impl Default for MaskOptions {
    fn default() -> Self {
        MaskOptions { erosion: Some(Erosion::default()), min_valid_depth_pixels: 100 }
    }
}

/// An object that passed validation.
#[derive(Debug, Clone)]
pub struct ValidObject {
    /// The object's mask (not eroded).
    pub mask: ObjectMask,
    /// Pixels under the eroded mask with valid depth.
    pub valid_depth_pixels: usize,
}

/// Check one object against the frame: its eroded-mask pixels with valid
/// depth, or why it is left out. Works on the mask's runs: a mask of a few
/// pixels is refused at the cost of its pixels, before any full-frame buffer.
pub fn check_object(frame: &RgbdFrame, m: &ObjectMask, opts: &MaskOptions) -> std::result::Result<usize, SkipReason> {
    if (m.width, m.height) != (frame.width, frame.height) {
        return Err(SkipReason::WrongSize { mask: (m.width, m.height), frame: (frame.width, frame.height) });
    }
    let before = m.pixel_count();
    if before == 0 {
        return Err(SkipReason::Empty);
    }
    let eroded = match opts.erosion {
        Some(e) => erode_runs(m.runs(), m.height, e),
        None => m.runs().to_vec(),
    };
    if eroded.is_empty() {
        return Err(SkipReason::EmptyAfterErosion { before });
    }
    let w = frame.width;
    let valid = eroded
        .iter()
        .map(|r| {
            let i = r.y as usize * w + r.x as usize;
            frame.depth_m[i..i + r.len as usize].iter().filter(|&&z| depth_valid(z)).count()
        })
        .sum();
    let min = opts.min_valid_depth_pixels.max(1);
    if valid < min {
        return Err(SkipReason::TooFewValidDepth { valid, min });
    }
    Ok(valid)
}

/// Check every object against the frame ([`check_object`]); failures become skips.
pub fn validate_objects(frame: &RgbdFrame, objects: Vec<ObjectMask>, opts: &MaskOptions) -> (Vec<ValidObject>, Vec<MaskSkip>) {
    let mut ok = Vec::new();
    let mut skips = Vec::new();
    for m in objects {
        match check_object(frame, &m, opts) {
            Ok(valid) => ok.push(ValidObject { mask: m, valid_depth_pixels: valid }),
            Err(reason) => skips.push(MaskSkip { label: m.label.clone(), reason }),
        }
    }
    (ok, skips)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dataset::frame::Intrinsics;

    #[test]
    fn load_masks_reads_a_map_or_binary_files() {
        let d = crate::util::testing::tmp("load-masks");
        let ids = image::GrayImage::from_fn(4, 3, |x, _| image::Luma([if x < 2 { 3 } else { 9 }]));
        ids.save(d.join("ids.png")).unwrap();
        let one = image::GrayImage::from_fn(4, 3, |x, y| image::Luma([if x == y { 255 } else { 0 }]));
        one.save(d.join("a.png")).unwrap();
        one.save(d.join("b.png")).unwrap();
        let (m, skip) = load_masks(&[d.join("ids.png")], Some(&[9, 5])).unwrap();
        assert_eq!((m.len(), m[0].id, m[0].pixel_count()), (1, Some(9), 6));
        assert_eq!(skip, vec![MaskSkip { label: "id 5".into(), reason: SkipReason::IdAbsent }]);
        let (m, _) = load_masks(&[d.join("a.png"), d.join("b.png")], None).unwrap();
        assert_eq!((m.len(), m[1].label.as_str(), m[1].pixel_count()), (2, "b.png", 3));
        let e = load_masks(&[d.join("a.png"), d.join("b.png")], Some(&[1])).unwrap_err().to_string();
        assert!(e.contains("--objects"), "{e}");
        assert!(load_masks(&[], None).unwrap_err().to_string().contains("--masks"));
        let _ = std::fs::remove_dir_all(&d);
    }

    fn frame(w: usize, h: usize, depth: impl Fn(usize, usize) -> f32) -> RgbdFrame {
        let mut d = vec![0f32; w * h];
        for y in 0..h {
            for x in 0..w {
                d[y * w + x] = depth(x, y);
            }
        }
        RgbdFrame {
            width: w,
            height: h,
            rgb: vec![0; w * h * 3],
            depth_m: d,
            intrinsics: Intrinsics { fx: 100.0, fy: 100.0, cx: w as f64 / 2.0, cy: h as f64 / 2.0 },
            rgb_path: PathBuf::new(),
            depth_path: PathBuf::new(),
            intrinsics_source: "test".into(),
            depth_scale_m: 0.001,
        }
    }

    /// Reference erosion straight from the definition.
    fn erode_naive(m: &[bool], w: usize, h: usize, k: usize) -> Vec<bool> {
        let lo = (k / 2) as isize;
        let mut out = vec![false; w * h];
        for y in 0..h as isize {
            for x in 0..w as isize {
                let mut all = true;
                for dy in -lo..(k as isize - lo) {
                    for dx in -lo..(k as isize - lo) {
                        let (xx, yy) = (x + dx, y + dy);
                        if xx < 0 || yy < 0 || xx >= w as isize || yy >= h as isize || !m[(yy as usize) * w + xx as usize] {
                            all = false;
                        }
                    }
                }
                out[y as usize * w + x as usize] = all;
            }
        }
        out
    }

    #[test]
    fn erosion_matches_definition() {
        let (w, h) = (23, 17);
        let mut s = 12345u64;
        let m: Vec<bool> = (0..w * h)
            .map(|_| {
                s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                !(s >> 33).is_multiple_of(7)
            })
            .collect();
        for k in [2, 3, 4, 5] {
            assert_eq!(erode(&m, w, h, Erosion { kernel: k, iterations: 1 }), erode_naive(&m, w, h, k), "k={k}");
        }
        // On runs: the same pixels for every kernel and pass count, in the frame or at its borders.
        let om = ObjectMask::from_bools(None, "m", w, h, &m);
        assert_eq!(om.to_bools(), m);
        for (k, it) in [(1, 1), (2, 1), (3, 1), (4, 1), (5, 1), (3, 2), (5, 0), (2, 3)] {
            let e = Erosion { kernel: k, iterations: it };
            let runs = erode_runs(om.runs(), h, e);
            assert_eq!(ObjectMask::from_runs(None, "r", w, h, runs).to_bools(), erode(&m, w, h, e), "k={k} it={it}");
        }
        let twice = erode(&m, w, h, Erosion { kernel: 3, iterations: 2 });
        assert_eq!(twice, erode_naive(&erode_naive(&m, w, h, 3), w, h, 3));
        // A 10×10 block loses 2 px per side with k = 5; the border counts as background.
        let mut b = vec![false; 20 * 20];
        for y in 5..15 {
            for x in 0..10 {
                b[y * 20 + x] = true;
            }
        }
        let e = erode(&b, 20, 20, Erosion::default());
        assert_eq!(e.iter().filter(|&&v| v).count(), 6 * 6); // x 2..8 (border side too), y 7..13
        let runs = erode_runs(ObjectMask::from_bools(None, "b", 20, 20, &b).runs(), 20, Erosion::default());
        assert_eq!(ObjectMask::from_runs(None, "b", 20, 20, runs).to_bools(), e);
        assert!(e[7 * 20 + 2] && !e[7 * 20 + 1] && !e[6 * 20 + 4]);
    }

    #[test]
    fn instance_map_selection_and_validation() {
        let dir = crate::util::testing::tmp("masks");
        let (w, h) = (40u32, 30u32);
        // id 3: big block with depth; id 5: 2-px thin line; id 700 (16-bit): block without depth.
        let lab = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_fn(w, h, |x, y| {
            image::Luma([if (5..20).contains(&x) && (5..20).contains(&y) {
                3
            } else if (y == 25 || y == 26) && x < 30 {
                5
            } else if (25..38).contains(&x) && (2..15).contains(&y) {
                700
            } else {
                0
            }])
        });
        let p16 = dir.join("labels16.png");
        lab.save(&p16).unwrap();
        let map = InstanceMap::open(&p16).unwrap();
        assert_eq!(map.present_ids(), vec![3, 5, 700]);
        // Each instance's runs hold exactly the pixels of its id.
        let (all, none) = map.objects(None);
        assert!(none.is_empty());
        assert_eq!(all.iter().map(|o| o.id.unwrap()).collect::<Vec<_>>(), map.present_ids());
        for o in &all {
            let expected: Vec<bool> = map.ids.iter().map(|&v| Some(v) == o.id).collect();
            assert_eq!(o.to_bools(), expected, "{}", o.label);
        }
        let f = frame(40, 30, |x, _| if x < 22 { 0.8 } else { 0.0 });
        let (objs, skips) = map.objects(Some(&[3, 5, 700, 9, 0]));
        assert_eq!(objs.len(), 3);
        assert_eq!(skips.iter().map(|s| s.reason.clone()).collect::<Vec<_>>(), vec![SkipReason::IdAbsent, SkipReason::Background]);
        let (ok, skips) = validate_objects(&f, objs, &MaskOptions::default());
        assert_eq!(ok.len(), 1);
        assert_eq!(ok[0].mask.id, Some(3));
        assert_eq!(ok[0].valid_depth_pixels, 11 * 11);
        assert!(matches!(skips[0].reason, SkipReason::EmptyAfterErosion { before: 60 }));
        assert_eq!(skips[1].reason, SkipReason::TooFewValidDepth { valid: 0, min: 100 });
        assert!(skips[1].to_string().contains("id 700"));

        // 8-bit map; wrong size against the frame.
        let lab8 = image::GrayImage::from_fn(20, 10, |x, _| image::Luma([if x > 3 { 2 } else { 0 }]));
        let p8 = dir.join("labels8.png");
        lab8.save(&p8).unwrap();
        let (objs, _) = InstanceMap::open(&p8).unwrap().objects(None);
        let (ok, skips) = validate_objects(&f, objs, &MaskOptions::default());
        assert!(ok.is_empty());
        assert_eq!(skips[0].reason, SkipReason::WrongSize { mask: (20, 10), frame: (40, 30) });

        // An RGB image is not an id map.
        image::RgbImage::new(4, 4).save(dir.join("rgb.png")).unwrap();
        assert!(InstanceMap::open(&dir.join("rgb.png")).unwrap_err().to_string().contains("single-channel"));

        // Binary masks: grey non-zero, and RGBA with alpha.
        let bm = image::GrayImage::from_fn(40, 30, |x, y| image::Luma([if x > 10 && y > 10 { 255 } else { 0 }]));
        bm.save(dir.join("obj.png")).unwrap();
        let m = load_binary_mask(&dir.join("obj.png")).unwrap();
        assert_eq!(m.pixel_count(), 29 * 19);
        assert_eq!(m.label, "obj.png");
        let rgba = image::RgbaImage::from_fn(40, 30, |x, _| image::Rgba([9, 9, 9, if x < 5 { 255 } else { 0 }]));
        rgba.save(dir.join("cut.png")).unwrap();
        assert_eq!(load_binary_mask(&dir.join("cut.png")).unwrap().pixel_count(), 5 * 30);
        // Several files: an unreadable one is skipped, the others load.
        let (ms, sk) = load_binary_masks(&[dir.join("obj.png"), dir.join("missing.png"), dir.join("cut.png")]);
        assert_eq!(ms.len(), 2);
        assert!(matches!(&sk[0].reason, SkipReason::Unreadable(_)) && sk[0].label.contains("missing.png"));
        // Empty mask is a skip, not an error.
        let empty = ObjectMask::from_bools(None, "e", 40, 30, &[false; 1200]);
        let (_, skips) = validate_objects(&f, vec![empty], &MaskOptions::default());
        assert_eq!(skips[0].reason, SkipReason::Empty);
    }

    #[test]
    fn many_one_pixel_instances_cost_their_pixels() {
        // 60×50 map, an instance on every other pixel of every other row: 750 instances.
        let (w, h) = (60usize, 50usize);
        let mut ids = vec![0u32; w * h];
        let mut n = 0;
        for y in (0..h).step_by(2) {
            for x in (0..w).step_by(2) {
                n += 1;
                ids[y * w + x] = n;
            }
        }
        let map = InstanceMap { width: w, height: h, ids, path: PathBuf::from("many.png") };
        let (objs, skips) = map.objects(None);
        assert!(skips.is_empty());
        assert_eq!(objs.len(), n as usize);
        assert!(objs.iter().all(|o| o.runs().len() == 1 && o.pixel_count() == 1));
        let f = frame(w, h, |_, _| 1.0);
        let (ok, skips) = validate_objects(&f, objs, &MaskOptions::default());
        assert!(ok.is_empty());
        assert!(skips.iter().all(|s| s.reason == SkipReason::EmptyAfterErosion { before: 1 }), "{:?}", skips[0]);
        // Without erosion a pixel is too few valid-depth pixels.
        let (o, _) = map.objects(Some(&[7]));
        let opts = MaskOptions { erosion: None, ..Default::default() };
        assert_eq!(check_object(&f, &o[0], &opts), Err(SkipReason::TooFewValidDepth { valid: 1, min: 100 }));
    }
}
