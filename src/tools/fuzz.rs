//! Fuzz targets: one entry point per parser recon implements itself, shared by
//! the coverage-guided fuzzer (`fuzz/`, cargo-fuzz) and the bounded
//! stable-toolchain pass the tests run ([`mutate`]d inputs from the corpus in
//! `fuzz/corpus/<target>/`). A target returns the parser's `Result`; what
//! the fuzzers check is that it returns at all: no panic, no hang, no
//! allocation beyond [`alloc_bound`].

use crate::dataset::frame::{intrinsics_from_bytes, CameraFormat};
use crate::{Error, Result};
use std::path::{Path, PathBuf};

/// Every fuzzed parser.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Target {
    /// A `.safetensors` checkpoint: header checks, the mapped load of each tensor.
    Safetensors,
    /// A torch `.pt` archive: zip, the pickle subset, each tensor's load.
    Pt,
    /// A MAT v5 file, then the YCB-Video intrinsics in it.
    MatV5,
    /// A PLY mesh (ASCII or binary) with its colours.
    Ply,
    /// A `recon scene` input (`scene.json`).
    SceneJson,
    /// A BOP `scene_gt.json` (with a fixed valid camera file and model).
    BopSceneGt,
    /// A BOP `scene_camera.json` (with a fixed valid GT file and model).
    BopSceneCamera,
    /// A BOP `models_info.json` (with fixed valid scene files and model).
    BopModelsInfo,
    /// An architecture file (`models/recgen-*.json`), with its memory bound.
    Architecture,
    /// A depth sensor model (`models/sensors/*.json`).
    Sensor,
    /// A material table (`models/materials.json`).
    Materials,
    /// A `recon eval --predictions` file.
    Predictions,
    /// A scene-variations spec (`recon scene --spec`).
    VariationSpec,
    /// A frame's intrinsics file (JSON).
    IntrinsicsJson,
    /// A frame's intrinsics file (YAML subset).
    IntrinsicsYaml,
    /// A user asset mesh in Wavefront OBJ.
    Obj,
    /// A user asset mesh in binary glTF (GLB).
    Glb,
    /// The physics JSON beside a user asset.
    AssetPhysics,
}

impl Target {
    pub const ALL: [Target; 18] = [
        Target::Safetensors,
        Target::Pt,
        Target::MatV5,
        Target::Ply,
        Target::SceneJson,
        Target::BopSceneGt,
        Target::BopSceneCamera,
        Target::BopModelsInfo,
        Target::Architecture,
        Target::Sensor,
        Target::Materials,
        Target::Predictions,
        Target::VariationSpec,
        Target::IntrinsicsJson,
        Target::IntrinsicsYaml,
        Target::Obj,
        Target::Glb,
        Target::AssetPhysics,
    ];

    /// The target's name: its corpus folder and its cargo-fuzz binary.
    pub fn name(self) -> &'static str {
        match self {
            Target::Safetensors => "safetensors",
            Target::Pt => "pt",
            Target::MatV5 => "matv5",
            Target::Ply => "ply",
            Target::SceneJson => "scene_json",
            Target::BopSceneGt => "bop_scene_gt",
            Target::BopSceneCamera => "bop_scene_camera",
            Target::BopModelsInfo => "bop_models_info",
            Target::Architecture => "architecture",
            Target::Sensor => "sensor",
            Target::Materials => "materials",
            Target::Predictions => "predictions",
            Target::VariationSpec => "variation_spec",
            Target::IntrinsicsJson => "intrinsics_json",
            Target::IntrinsicsYaml => "intrinsics_yaml",
            Target::Obj => "obj",
            Target::Glb => "glb",
            Target::AssetPhysics => "asset_physics",
        }
    }

    pub fn from_name(s: &str) -> Option<Target> {
        Target::ALL.into_iter().find(|t| t.name() == s)
    }

    /// Text formats get number substitutions among their mutations.
    pub fn is_text(self) -> bool {
        !matches!(self, Target::Safetensors | Target::Pt | Target::MatV5 | Target::Glb)
    }
}

/// The most bytes a target may hold live at once for an input of `len`
/// bytes: 256 MiB plus 32 bytes per input byte (the largest legitimate
/// cases: a MAT v5 zlib stream inflating to its 64 MiB bound, read in a
/// doubling buffer; f16 tensors widened to f32).
pub fn alloc_bound(len: usize) -> usize {
    (256 << 20) + 32 * len
}

/// A scratch folder for the targets that read files, one per thread (the
/// fuzzers and tests call targets from several threads).
fn scratch() -> Result<PathBuf> {
    let id = format!("{:?}", std::thread::current().id()).chars().filter(char::is_ascii_digit).collect::<String>();
    let d = std::env::temp_dir().join(format!("recon-fuzz-{}-{id}", std::process::id()));
    std::fs::create_dir_all(&d).map_err(|e| Error::io(&d, e))?;
    Ok(d)
}

fn write(dir: &Path, name: &str, data: &[u8]) -> Result<PathBuf> {
    let p = dir.join(name);
    std::fs::write(&p, data).map_err(|e| Error::io(&p, e))?;
    Ok(p)
}

const BOP_GT: &str = r#"{"0": [{"cam_R_m2c": [1,0,0,0,1,0,0,0,1], "cam_t_m2c": [0,0,500], "obj_id": 1}]}"#;
// Cameras for every image the scene_gt seed names (0 and 3), so the seed itself parses.
const BOP_CAMERA: &str = r#"{"0": {"cam_K": [500,0,32,0,500,24,0,0,1], "depth_scale": 1.0},
"3": {"cam_K": [500,0,32,0,500,24,0,0,1], "depth_scale": 1.0}}"#;
const BOP_INFO: &str = r#"{"1": {"diameter": 100.0}}"#;
const BOP_PLY: &str = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n\
element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n10 0 0\n0 10 0\n3 0 1 2\n";

/// A BOP split with one scene and one model, `which` replaced by `data`.
fn bop(data: &[u8], which: &str) -> Result<()> {
    let root = scratch()?.join("bop");
    let scene = root.join("test/000000");
    let models = root.join("models");
    for d in [&scene, &models] {
        std::fs::create_dir_all(d).map_err(|e| Error::io(d, e))?;
    }
    let pick = |name: &str, default: &str| if name == which { data.to_vec() } else { default.as_bytes().to_vec() };
    write(&scene, "scene_gt.json", &pick("scene_gt", BOP_GT))?;
    write(&scene, "scene_camera.json", &pick("scene_camera", BOP_CAMERA))?;
    write(&models, "models_info.json", &pick("models_info", BOP_INFO))?;
    write(&models, "obj_000001.ply", BOP_PLY.as_bytes())?;
    crate::dataset::bop::load_bop(&root.join("test"), &models).map(|_| ())
}

/// Run one target on one input.
pub fn run(target: Target, data: &[u8]) -> Result<()> {
    let text = || String::from_utf8_lossy(data).into_owned();
    match target {
        Target::Safetensors => {
            let p = write(&scratch()?, "w.safetensors", data)?;
            let c = crate::weights::Checkpoint::open(&p, None)?;
            for name in c.tensors().keys() {
                c.get(name)?;
            }
            Ok(())
        }
        Target::Pt => {
            let p = write(&scratch()?, "w.pt", data)?;
            let c = crate::weights::Checkpoint::open(&p, None)?;
            for name in c.tensors().keys() {
                c.get(name)?;
            }
            Ok(())
        }
        Target::MatV5 => intrinsics_from_bytes(data, CameraFormat::Mat, "fuzz.mat").map(|_| ()),
        Target::Ply => crate::dataset::ply::parse_ply_with_colors(data, "fuzz.ply").map(|_| ()),
        Target::SceneJson => {
            // The seeds name these two meshes; SceneFile::load checks they exist.
            let dir = scratch()?;
            write(&dir, "box_mm.ply", BOP_PLY.as_bytes())?;
            write(&dir, "can.ply", BOP_PLY.as_bytes())?;
            crate::sim::SceneFile::load(&write(&dir, "scene.json", data)?).map(|_| ())
        }
        Target::BopSceneGt => bop(data, "scene_gt"),
        Target::BopSceneCamera => bop(data, "scene_camera"),
        Target::BopModelsInfo => bop(data, "models_info"),
        Target::Architecture => {
            let p = write(&scratch()?, "arch.json", data)?;
            let c = crate::model::RecGenConfig::load(&p)?;
            c.min_memory_bytes();
            c.ss_flow_config();
            Ok(())
        }
        Target::Sensor => crate::sensor::SensorModel::from_json_str(&text(), "sensor.json").map(|_| ()),
        Target::Materials => crate::sim::MaterialTable::from_json_str(&text(), "materials.json").map(|_| ()),
        Target::Predictions => {
            let p = write(&scratch()?, "predictions.json", data)?;
            crate::eval::read_predictions(&p).map(|_| ())
        }
        Target::VariationSpec => crate::sim::VariationSpec::parse(&text(), "variations.json").map(|_| ()),
        Target::IntrinsicsJson => intrinsics_from_bytes(data, CameraFormat::Json, "camera.json").map(|_| ()),
        Target::IntrinsicsYaml => intrinsics_from_bytes(data, CameraFormat::Yaml, "meta.yml").map(|_| ()),
        Target::Obj => crate::dataset::parse_mesh(data, crate::dataset::MeshFormat::Obj, "asset.obj").map(|_| ()),
        Target::Glb => crate::dataset::parse_mesh(data, crate::dataset::MeshFormat::Glb, "asset.glb").map(|_| ()),
        Target::AssetPhysics => {
            let table = crate::sim::MaterialTable::builtin();
            crate::sim::AssetPhysics::parse(&text(), "asset.json", Some(&table)).map(|_| ())
        }
    }
}

/// Numbers that stress size fields and arithmetic, substituted into text inputs.
const HOSTILE_NUMBERS: [&str; 12] = [
    "0",
    "-1",
    "1e308",
    "-1e308",
    "4294967296",
    "18446744073709551615",
    "99999999999999999999999",
    "1000000000000",
    "NaN",
    "2147483648",
    "1e-320",
    "100000",
];

/// Deterministic mutations of the corpus: the `i`-th input derived from
/// `seeds` (bit flips, byte overwrites with boundary values, truncation,
/// duplicated and deleted ranges, splices of two seeds, boundary integers
/// written over 1, 2, 4 or 8 bytes, and for text formats number
/// substitutions), a few stacked per input.
pub fn mutate(seeds: &[Vec<u8>], i: u64, text: bool) -> Vec<u8> {
    let mut rng = crate::rng::SeededRng::new(0x5eed_f022 ^ i.wrapping_mul(0x9E37_79B9_7F4A_7C15));
    let mut pick = |n: usize| if n == 0 { 0 } else { (rng.next_u64() % n as u64) as usize };
    if seeds.is_empty() {
        return Vec::new();
    }
    let mut d = seeds[pick(seeds.len())].clone();
    let rounds = 1 + pick(4);
    for _ in 0..rounds {
        let len = d.len();
        match pick(if text { 9 } else { 8 }) {
            0 if len > 0 => {
                let p = pick(len);
                d[p] ^= 1 << pick(8);
            }
            1 if len > 0 => {
                let p = pick(len);
                d[p] = [0x00, 0xff, 0x7f, 0x80, b'\n', b'"', b'[', b'{'][pick(8)];
            }
            2 => d.truncate(pick(len + 1)),
            3 if len > 0 => {
                let (a, b) = (pick(len), pick(len));
                let (a, b) = (a.min(b), a.max(b));
                let chunk = d[a..b].to_vec();
                let at = pick(len + 1);
                d.splice(at..at, chunk);
            }
            4 if len > 0 => {
                let (a, b) = (pick(len), pick(len));
                d.drain(a.min(b)..a.max(b));
            }
            5 => {
                let other = &seeds[pick(seeds.len())];
                let (a, b) = (pick(len + 1), pick(other.len() + 1));
                d.truncate(a);
                d.extend_from_slice(&other[b..]);
            }
            6 if len > 0 => {
                let w = [1usize, 2, 4, 8][pick(4)];
                let v: u64 = [0, u64::MAX, 1 << 31, 1 << 32, u32::MAX as u64, 1 << 40, 0x7fff_ffff_ffff_ffff][pick(7)];
                let p = pick(len);
                let bytes = if pick(2) == 0 { v.to_le_bytes() } else { v.to_be_bytes() };
                let n = w.min(len - p);
                d[p..p + n].copy_from_slice(&bytes[..n]);
            }
            7 if len > 0 => {
                // Repeat a range many times (large counts, deep nesting).
                let (a, n) = (pick(len), 1 + pick(16));
                let b = (a + n).min(len);
                let chunk = d[a..b].to_vec();
                let reps = 1 + pick(512);
                let mut ins = Vec::with_capacity(chunk.len() * reps);
                for _ in 0..reps {
                    ins.extend_from_slice(&chunk);
                }
                d.splice(b..b, ins);
            }
            8 => {
                // Replace one run of digits with a hostile number.
                let runs: Vec<(usize, usize)> = {
                    let mut v = Vec::new();
                    let mut k = 0;
                    while k < len {
                        if d[k].is_ascii_digit() {
                            let s = k;
                            while k < len && (d[k].is_ascii_digit() || d[k] == b'.') {
                                k += 1;
                            }
                            v.push((s, k));
                        } else {
                            k += 1;
                        }
                    }
                    v
                };
                if !runs.is_empty() {
                    let (a, b) = runs[pick(runs.len())];
                    let n = HOSTILE_NUMBERS[pick(HOSTILE_NUMBERS.len())];
                    d.splice(a..b, n.bytes());
                }
            }
            _ => {}
        }
    }
    d
}

/// The corpus files of a target (sorted, so the pass is deterministic).
pub fn corpus(dir: &Path) -> Result<Vec<Vec<u8>>> {
    let mut files: Vec<PathBuf> =
        std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?.filter_map(|e| e.ok().map(|e| e.path())).filter(|p| p.is_file()).collect();
    files.sort();
    files.iter().map(|p| std::fs::read(p).map_err(|e| Error::io(p, e))).collect()
}
