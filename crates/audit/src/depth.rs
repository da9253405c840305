//! Depth audit: pixels of GT objects → residual table against a sensor model.
use crate::table::{Column, ResidualTable};
use recon_core::sensor::{Base, Covariate, PixelCovariates, SensorModel, Target};

/// One compared pixel: its covariates (after the model's edge fattening, as the
/// simulator evaluates them; `depth` = simulated z) and the measured depth in metres
/// (0 or non-finite = missing).
#[derive(Clone, Copy, Debug)]
pub struct PixelSample {
    /// Covariates of the pixel, as the simulator sees them.
    pub cov: PixelCovariates,
    /// Measured depth in metres (0 or non-finite: missing).
    pub measured: f64,
}

/// Spread of the disparity quantisation in z at depth z (uniform rounding: step²/12).
pub fn quantisation_sd(model: &SensorModel, z: f64) -> f64 {
    match &model.base {
        Base::Stereo { focal_px, baseline_m, subpixel, .. } if *subpixel > 0.0 => z * z * subpixel / (focal_px * baseline_m) / 12f64.sqrt(),
        _ => 0.0,
    }
}

/// Builds the residual table of `pixels` against `model`: simulated = depth + the
/// model's bias, the model's sd floor (base ⊕ quantisation) and its existing noise and
/// dropout effects as offsets, so the search looks for what the model lacks. Pixels
/// the model declares out of range are left out. Units are frames (`cov.frame`).
pub fn residual_table(model: &SensorModel, pixels: &[PixelSample], source: &str) -> ResidualTable {
    let mut t = ResidualTable { source: source.to_string(), value_unit: "m".into(), ..Default::default() };
    let mut frames: Vec<i64> = pixels.iter().map(|p| p.cov.frame).collect();
    frames.sort_unstable();
    frames.dedup();
    t.unit_names = frames.iter().map(|f| f.to_string()).collect();
    let mut cols: Vec<Vec<f64>> = vec![vec![]; Covariate::ALL.len()];
    for p in pixels {
        let c = &p.cov;
        let z = c.depth;
        if !(z > 0.0) || (model.min_depth_m > 0.0 && z < model.min_depth_m) || (model.max_depth_m > 0.0 && z > model.max_depth_m) {
            continue;
        }
        t.measured.push(if p.measured.is_finite() && p.measured > 0.0 { p.measured } else { f64::NAN });
        t.simulated.push(z + model.bias(c));
        let b = model.base_sd(z);
        let q = quantisation_sd(model, z);
        t.sd_floor.push((b * b + q * q).sqrt());
        t.sd_clamp.push(q);
        t.sd_offset.push(model.effects.iter().filter(|e| e.target == Target::Noise).map(|e| e.eval(c)).sum());
        t.p_offset.push(model.effects.iter().filter(|e| e.target == Target::Dropout).map(|e| e.eval(c)).sum());
        t.unit.push(frames.binary_search(&c.frame).expect("frame listed"));
        for (k, cv) in Covariate::ALL.iter().enumerate() {
            cols[k].push(c.get(*cv));
        }
    }
    for (k, cv) in Covariate::ALL.iter().enumerate() {
        let values = std::mem::take(&mut cols[k]);
        t.columns.push(if cv.is_categorical() { Column::categorical(cv.name(), values) } else { Column::numeric(cv.name(), values) });
    }
    t
}

/// How the measured frames are paired with simulation.
#[derive(Clone, Debug)]
pub struct DepthOptions {
    /// Object pixels kept per frame (a seeded random subset; all when fewer).
    pub max_pixels_per_frame: usize,
    /// Seed of the per-frame pixel subsets.
    pub seed: u64,
    /// Use only the first N frames (all when None).
    pub max_frames: Option<usize>,
}

impl Default for DepthOptions {
    fn default() -> Self {
        DepthOptions { max_pixels_per_frame: 3000, seed: 0, max_frames: None }
    }
}

/// Pixels of a dataset paired with their simulation, and how they were obtained.
pub struct Collected {
    pub pixels: Vec<PixelSample>,
    pub frames: usize,
    /// Object pixels over all frames before subsampling.
    pub object_pixels: usize,
    /// How the simulated depth was obtained.
    pub simulation: String,
    /// Frame names (`scene/frame`) in covariate `frame` order.
    pub frame_names: Vec<String>,
    /// Simulated images of each frame (covariate `frame` order), after the model's edge
    /// fattening: what the mechanism inference warps.
    pub sims: Vec<recon_core::sensor::SimFrame>,
}

/// Reads a dataset (BOP, e.g. from `recon synth`, or the YCB-Video layout; see
/// `eval::bop::load_dataset`), simulates every frame's GT scene and pairs it with the
/// measured depth on the visible pixels of the GT objects. The simulation is the GT
/// meshes ray-cast at the GT poses (`synth::render`); YCB-Video ships point clouds, not
/// meshes, so there the dataset's own GT rendering (`vertmap` in `-meta.mat`: the
/// model-frame point of every object pixel) is posed instead, with normals from its
/// neighbours. Covariates are those of `synth::Rendered::covariates_full` (intensity from
/// the measured colour image, edges of the GT objects' depth), after the model's edge
/// fattening. `frame` is the frame's position in the dataset (scenes and images sorted).
pub fn collect(dir: &std::path::Path, model: &SensorModel, opts: &DepthOptions) -> recon_core::Result<Collected> {
    use recon_core::dataset::bop::load_dataset;
    use recon_core::dataset::frame::{load_depth_u16, load_rgb};
    use recon_core::Error;
    let ds = load_dataset(dir)?;
    let ycbv = dir.join("models_points_xyz").is_dir();
    let mut meshes = std::collections::BTreeMap::new();
    if !ycbv {
        for (id, m) in &ds.models {
            if m.mesh.faces.is_empty() {
                return Err(Error::input(
                    m.path.display().to_string(),
                    format!("model {id} has no faces: the depth audit renders triangle meshes"),
                ));
            }
            meshes.insert(*id, recon_synth::RenderMesh::from_trimesh(&m.mesh, &m.path.display().to_string())?);
        }
    }
    let n = opts.max_frames.unwrap_or(usize::MAX).min(ds.frames.len());
    let mut out = Collected { pixels: vec![], frames: n, object_pixels: 0, simulation: String::new(), frame_names: vec![], sims: vec![] };
    out.simulation = if ycbv {
        "YCB-Video GT rendering (vertmap of -meta.mat) posed by the GT; normals from neighbouring pixels".into()
    } else {
        "GT meshes ray-cast at the GT poses (synth renderer)".into()
    };
    for (fi, f) in ds.frames.iter().take(n).enumerate() {
        let (rgb_path, depth_path) = if ycbv {
            let d = ds.root.join(&f.scene);
            (d.join(format!("{:06}-color.png", f.frame)), d.join(format!("{:06}-depth.png", f.frame)))
        } else {
            let d = ds.root.join(&f.scene);
            let png = d.join("rgb").join(format!("{:06}.png", f.frame));
            let rgb = if png.is_file() { png } else { d.join("rgb").join(format!("{:06}.jpg", f.frame)) };
            (rgb, d.join("depth").join(format!("{:06}.png", f.frame)))
        };
        let (rgb, w, h) = load_rgb(&rgb_path)?;
        let (raw, dw, dh) = load_depth_u16(&depth_path)?;
        if (dw, dh) != (w, h) {
            return Err(Error::input(depth_path.display().to_string(), format!("depth is {dw}×{dh}, the colour image is {w}×{h}")));
        }
        let k = recon_core::dataset::frame::Intrinsics::new(f.k[0][0], f.k[1][1], f.k[0][2], f.k[1][2])?;
        let rendered = if ycbv {
            let meta = ds.root.join(&f.scene).join(format!("{:06}-meta.mat", f.frame));
            ycbv_rendering(&meta, f, k, w, h, &rgb)?
        } else {
            let insts: Vec<recon_synth::Instance> =
                f.gt.iter()
                    .map(|g| recon_synth::Instance::new(&meshes[&g.obj_id], recon_core::math::Similarity::rigid(g.r, g.t), g.obj_id as i64))
                    .collect();
            recon_core::render::render(&insts, &recon_synth::Camera::new(w, h, k), &Default::default())?
        };
        let covs = model.fattened(&rendered.covariates_full(fi as i64, Some(&rgb), None), w, h);
        let mut idx: Vec<usize> = (0..w * h).filter(|&i| rendered.index[i] >= 0 && covs[i].depth > 0.0).collect();
        out.object_pixels += idx.len();
        if idx.len() > opts.max_pixels_per_frame {
            // Partial Fisher–Yates with a per-frame seed, then back to raster order.
            let mut rng = recon_core::rng::SeededRng::new(opts.seed ^ (fi as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
            for j in 0..opts.max_pixels_per_frame {
                let r = j + (rng.next_u64() % (idx.len() - j) as u64) as usize;
                idx.swap(j, r);
            }
            idx.truncate(opts.max_pixels_per_frame);
            idx.sort_unstable();
        }
        let scale_m = f.depth_scale_m;
        for i in idx {
            out.pixels.push(PixelSample { cov: covs[i], measured: raw[i] as f64 * scale_m });
        }
        out.frame_names.push(format!("{}/{:06}", f.scene, f.frame));
        let pin = recon_core::sensor::Pinhole { fx: k.fx, fy: k.fy, cx: k.cx, cy: k.cy };
        out.sims.push(recon_core::sensor::sim_frame(&covs, w, h, pin));
    }
    if out.pixels.is_empty() {
        return Err(Error::input(dir.display().to_string(), "no GT object is visible in any frame"));
    }
    Ok(out)
}

/// A `Rendered` view of a YCB-Video frame from its `vertmap` (model-frame coordinates of
/// every object pixel, rendered by the dataset authors from the GT) and `label` map.
fn ycbv_rendering(
    meta: &std::path::Path,
    f: &recon_core::dataset::bop::Frame,
    k: recon_core::dataset::frame::Intrinsics,
    w: usize,
    h: usize,
    rgb: &[u8],
) -> recon_core::Result<recon_synth::Rendered> {
    use recon_core::Error;
    let file = meta.display().to_string();
    let mat = recon_core::dataset::matv5::MatFile::open(meta)?;
    let vm = mat.require("vertmap", &file)?;
    if vm.dims != [h, w, 3] {
        return Err(Error::config(&file, "vertmap", format!("dims {:?}, expected [{h}, {w}, 3]", vm.dims)));
    }
    let label_path = meta.with_file_name(meta.file_name().and_then(|s| s.to_str()).unwrap_or("").replace("-meta.mat", "-label.png"));
    let label = recon_core::util::open_image(&label_path, "label image")?.to_luma8();
    if (label.width() as usize, label.height() as usize) != (w, h) {
        return Err(Error::input(
            label_path.display().to_string(),
            format!("label is {}×{}, expected {w}×{h}", label.width(), label.height()),
        ));
    }
    let n = w * h;
    let mut pts = vec![[0.0f64; 3]; n];
    let mut index = vec![-1i32; n];
    let ids: Vec<i64> = f.gt.iter().map(|g| g.obj_id as i64).collect();
    for v in 0..h {
        for u in 0..w {
            let i = v * w + u;
            let c = label.get_pixel(u as u32, v as u32)[0] as i64;
            let Some(gi) = ids.iter().position(|&x| x == c) else { continue };
            let x = [0, 1, 2].map(|d| vm.data[v + h * (u + w * d)]);
            if x == [0.0; 3] {
                continue;
            }
            let g = &f.gt[gi];
            pts[i] = [0, 1, 2].map(|r| (0..3).map(|c| g.r[r][c] * x[c]).sum::<f64>() + g.t[r]);
            if pts[i][2] > 0.0 {
                index[i] = gi as i32;
            }
        }
    }
    // Normals from neighbouring points of the same object (central differences where
    // both neighbours exist, else one-sided), oriented towards the camera.
    let mut normal = vec![[0.0f32; 3]; n];
    let mut incidence = vec![0.0f32; n];
    let same = |i: usize, j: usize| index[j] == index[i];
    for v in 0..h {
        for u in 0..w {
            let i = v * w + u;
            if index[i] < 0 {
                continue;
            }
            let diff = |a: Option<usize>, b: Option<usize>| -> Option<[f64; 3]> {
                match (a.filter(|&a| same(i, a)), b.filter(|&b| same(i, b))) {
                    (Some(a), Some(b)) => Some([0, 1, 2].map(|d| pts[b][d] - pts[a][d])),
                    (Some(a), None) => Some([0, 1, 2].map(|d| pts[i][d] - pts[a][d])),
                    (None, Some(b)) => Some([0, 1, 2].map(|d| pts[b][d] - pts[i][d])),
                    _ => None,
                }
            };
            let du = diff((u > 0).then(|| i - 1), (u + 1 < w).then(|| i + 1));
            let dv = diff((v > 0).then(|| i - w), (v + 1 < h).then(|| i + w));
            let (Some(a), Some(b)) = (du, dv) else { continue };
            let mut nn = [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
            let len = (nn[0] * nn[0] + nn[1] * nn[1] + nn[2] * nn[2]).sqrt();
            if !(len > 0.0) {
                continue;
            }
            let ray = [(u as f64 - k.cx) / k.fx, (v as f64 - k.cy) / k.fy, 1.0];
            let rl = (ray[0] * ray[0] + ray[1] * ray[1] + 1.0).sqrt();
            let mut cosang = (nn[0] * ray[0] + nn[1] * ray[1] + nn[2] * ray[2]) / (len * rl);
            if cosang > 0.0 {
                nn = nn.map(|x| -x);
                cosang = -cosang;
            }
            normal[i] = nn.map(|x| (x / len) as f32);
            incidence[i] = cosang.abs().min(1.0).acos().to_degrees() as f32;
        }
    }
    Ok(recon_synth::Rendered {
        width: w,
        height: h,
        k,
        depth: pts.iter().zip(&index).map(|(p, &x)| if x >= 0 { p[2] as f32 } else { 0.0 }).collect(),
        index,
        ids,
        normal_cam: normal,
        normal_world: vec![[0.0; 3]; n],
        incidence,
        rgb: rgb.to_vec(),
        amodal: vec![],
    })
}
