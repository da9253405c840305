//! The released RecGen checkpoints end to end, offline: a Hugging Face cache
//! laid out as `huggingface_hub` leaves it (blobs named by SHA-256, snapshot
//! symlinks, refs/main) holds the release's files under their released names
//! (`pipeline.json`, `sparse-structure-ft-70k/…`, the `.pt` denoisers, the
//! TRELLIS decoders, the torch.hub DINOv2), made of tiny random modules with
//! the released tensor names. `recon infer` runs from it with HF_HUB_OFFLINE=1
//! through a copy of the embedded `recgen` manifest whose pins and tensor
//! lists are the tiny files' (`Manifest::with_tensors_from`, `with_pins_from`:
//! what `recon weights manifest` writes); every file is read through the
//! manifest, and a corrupted or missing file stops the run naming it.
#![cfg(unix)]
mod common;

use common::{repo, tmp};
use recon::model::{ModuleKey, RecGenConfig};
use recon::weights::hf_cache::sha256_file;
use recon::weights::Manifest;
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The embedded manifest's pinned revision: the snapshot the fake cache holds.
const COMMIT: &str = "bc0df7de2e43314830039a35a720731d4c4fac65";

/// Store `bytes` as huggingface_hub does: `blobs/<sha256>`, and
/// `snapshots/<COMMIT>/<path>` a relative symlink to it.
fn put(repo_dir: &Path, path: &str, bytes: &[u8]) {
    let blobs = repo_dir.join("blobs");
    std::fs::create_dir_all(&blobs).unwrap();
    let tmp_blob = blobs.join("incoming");
    std::fs::write(&tmp_blob, bytes).unwrap();
    let sha = sha256_file(&tmp_blob).unwrap();
    std::fs::rename(&tmp_blob, blobs.join(&sha)).unwrap();
    let link = repo_dir.join("snapshots").join(COMMIT).join(path);
    std::fs::create_dir_all(link.parent().unwrap()).unwrap();
    let up = "../".repeat(2 + path.matches('/').count());
    std::os::unix::fs::symlink(format!("{up}blobs/{sha}"), &link).unwrap();
}

fn json_bytes(v: &serde_json::Value) -> Vec<u8> {
    serde_json::to_vec_pretty(v).unwrap()
}

/// Random tiny weights of module `key`, keyed by the released tensor names.
fn weights(arch: &RecGenConfig, key: ModuleKey) -> BTreeMap<String, candle_core::Tensor> {
    recon::weights::registry::random_weights(&arch.module_args(key).unwrap(), 7 + key as u64, key.name()).unwrap()
}

fn safetensors_bytes(dir: &Path, key: ModuleKey, arch: &RecGenConfig) -> Vec<u8> {
    let p = dir.join(format!("{key}.safetensors"));
    recon::weights::init::write_safetensors(&weights(arch, key), &BTreeMap::new(), &p).unwrap();
    std::fs::read(&p).unwrap()
}

fn pt_bytes(dir: &Path, key: ModuleKey, arch: &RecGenConfig) -> Vec<u8> {
    let p = dir.join(format!("{key}.pt"));
    recon::weights::write_pt(&weights(arch, key), &p).unwrap();
    std::fs::read(&p).unwrap()
}

/// The fake cache under `root/hf/hub` and the two manifests (`root/recgen.json`
/// requiring `root/dinov2.json`) pinned to it.
fn release(root: &Path) -> (PathBuf, PathBuf) {
    let arch = RecGenConfig::load(&repo().join("models/recgen-tiny.json")).unwrap();
    let scratch = root.join("scratch");
    std::fs::create_dir_all(&scratch).unwrap();
    let hub = root.join("hf/hub");
    let rg = hub.join("models--TRI-ML--RecGen");
    let section = |key: ModuleKey| arch.module(key).unwrap().clone();
    let spec = |name: &str, key: ModuleKey| serde_json::json!({"name": name, "args": section(key).args});
    let sampler = |steps: usize| {
        serde_json::json!({"name": "FlowEulerGuidanceIntervalSampler", "args": {"sigma_min": 1e-5},
            "params": {"steps": steps, "cfg_strength": 7.5, "cfg_interval": [0.5, 1.0], "rescale_t": 3.0}})
    };
    let decoders = [
        ("ckpts/ss_dec_conv3d_16l8_fp16", "SparseStructureDecoder", ModuleKey::SsDecoder),
        ("ckpts/slat_dec_mesh_swin8_B_64l8m256c_fp16", "ElasticSLatMeshDecoder", ModuleKey::SlatDecMesh),
        ("ckpts/slat_dec_gs_swin8_B_64l8gs32_fp16", "ElasticSLatGaussianDecoder", ModuleKey::SlatDecGs),
    ];
    let models: serde_json::Map<String, serde_json::Value> = [
        ("sparse_structure_decoder", decoders[0].0),
        ("sparse_structure_flow_model", "ckpts/ss_flow_img_dit_L_16l8_fp16"),
        ("slat_decoder_gs", decoders[2].0),
        ("slat_decoder_rf", "ckpts/slat_dec_rf_swin8_B_64l8r16_fp16"),
        ("slat_decoder_mesh", decoders[1].0),
        ("slat_flow_model", "ckpts/slat_flow_img_dit_L_64l8p2_fp16"),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_string(), serde_json::json!(v)))
    .collect();
    put(
        &rg,
        "pipeline.json",
        &json_bytes(&serde_json::json!({"name": "TrellisImageTo3DPipeline", "args": {
            "models": models, "sparse_structure_sampler": sampler(3), "slat_sampler": sampler(2),
            "image_cond_model": "dinov2_vitl14_reg"}})),
    );
    put(&rg, "sparse-structure-ft-70k/stereo_denoiser_ema0.9999_step0070000.pt", &pt_bytes(&scratch, ModuleKey::SsFlow, &arch));
    put(
        &rg,
        "sparse-structure-ft-70k/stereo_config.json",
        &json_bytes(&serde_json::json!({"models": {"denoiser": spec("SparseStructurePoseFlowModel", ModuleKey::SsFlow)},
            "trainer": {"name": "MultiImageConditionedFlowMatchingCFGTrainer", "args": {"use_pose_normalization": true}}})),
    );
    let stats = |rel: &str| std::fs::read(arch.base_dir.join(rel)).unwrap();
    put(&rg, "sparse-structure-ft-70k/stereo_pose_stats.json", &stats(&arch.pose.ss_stats));
    put(&rg, "slat_denoiser_ema0.9999_step0075000.pt", &pt_bytes(&scratch, ModuleKey::SlatFlow, &arch));
    // A normalisation of its own, so the test sees it taken from the release.
    let norm =
        serde_json::json!({"mean": vec![0.25; arch.slat_normalization.mean.len()], "std": vec![1.5; arch.slat_normalization.std.len()]});
    put(
        &rg,
        "slat_config.json",
        &json_bytes(&serde_json::json!({"models": {"denoiser": spec("ElasticSLatCondFlowModel", ModuleKey::SlatFlow)},
            "dataset": {"args": {"use_pose_normalization": true, "normalization": norm}}})),
    );
    put(&rg, "slat_pose_stats.json", &stats(&arch.pose.slat_stats));
    for (stem, class, key) in decoders {
        put(&rg, &format!("{stem}.json"), &json_bytes(&spec(class, key)));
        put(&rg, &format!("{stem}.safetensors"), &safetensors_bytes(&scratch, key, &arch));
    }
    std::fs::create_dir_all(rg.join("refs")).unwrap();
    std::fs::write(rg.join("refs/main"), COMMIT).unwrap();
    // The torch.hub DINOv2 checkpoint where `recon weights fetch` puts URL files.
    let dino_dir = hub.join("recon-url/dinov2-vitl14-reg");
    std::fs::create_dir_all(&dino_dir).unwrap();
    let dino = pt_bytes(&scratch, ModuleKey::ImageCondModel, &arch);
    std::fs::write(dino_dir.join("dinov2_vitl14_reg4_pretrain.pth"), dino).unwrap();

    // The embedded manifests, with the tiny files' tensor lists and pins.
    let tiny = "models/recgen-tiny.json";
    let (dm, absent) = Manifest::load("dinov2-vitl14-reg").unwrap().with_tensors_from(&arch, tiny).unwrap().with_pins_from(&hub).unwrap();
    assert!(absent.is_empty(), "{absent:?}");
    let mut rm = Manifest::load("recgen").unwrap();
    assert_eq!(rm.revision.as_deref(), Some(COMMIT));
    assert_eq!(rm.requires, vec!["dinov2-vitl14-reg".to_string()]);
    rm.requires = vec!["dinov2.json".into()];
    let (rm, absent) = rm.with_tensors_from(&arch, tiny).unwrap().with_pins_from(&hub).unwrap();
    let optional: BTreeSet<&str> = rm.files.iter().filter(|f| f.optional).map(|f| f.path.as_str()).collect();
    assert!(absent.iter().all(|a| optional.contains(a.as_str())), "a needed file is missing from the fake release: {absent:?}");
    let (mp, dp) = (root.join("recgen.json"), root.join("dinov2.json"));
    std::fs::write(&mp, rm.to_pretty_json().unwrap()).unwrap();
    std::fs::write(&dp, dm.to_pretty_json().unwrap()).unwrap();
    (hub, mp)
}

/// `recon` offline on the fake cache (HF_HOME = root/hf; no other HF_* variable).
fn recon_offline(root: &Path, args: &[&str]) -> Output {
    let mut c = Command::new(env!("CARGO_BIN_EXE_recon"));
    c.args(args).current_dir(repo());
    for k in ["HF_HUB_CACHE", "HF_TOKEN", "HF_ENDPOINT"] {
        c.env_remove(k);
    }
    c.env("HF_HOME", root.join("hf")).env("HF_HUB_OFFLINE", "1");
    c.output().expect("running recon")
}

fn infer(root: &Path, manifest: &Path) -> Output {
    let out = root.join("out");
    recon_offline(
        root,
        &[
            "infer",
            "--rgbd",
            "data/sample/000001-color.png",
            "--masks",
            "data/sample/000001-label.png",
            "--objects",
            "8",
            "--weights",
            manifest.to_str().unwrap(),
            "--config",
            "models/recgen-tiny.json",
            "--steps",
            "1",
            "--max-faces",
            "0",
            "--out",
            out.to_str().unwrap(),
            "--json",
        ],
    )
}

#[test]
fn released_layout_runs_offline_from_the_hf_cache() {
    let root = tmp("released");
    let (hub, manifest) = release(&root);
    let rm = Manifest::load(manifest.to_str().unwrap()).unwrap();
    let dm = Manifest::load(root.join("dinov2.json").to_str().unwrap()).unwrap();

    // recon weights verify: every file present, pinned and of the listed tensors.
    let o = recon_offline(&root, &["weights", "verify", hub.to_str().unwrap(), "--manifest", manifest.to_str().unwrap()]);
    let table = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{table}\n{}", String::from_utf8_lossy(&o.stderr));
    assert!(table.contains("sha256 ok") && !table.contains("FAIL"), "{table}");

    let o = infer(&root, &manifest);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    let summary: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(summary["objects"].as_array().map(Vec::len), Some(1), "{summary}");
    // Every needed file of both manifests was read through the manifest, pinned and checked.
    let read = summary["weights"]["manifest_files"].as_array().expect("manifest_files");
    let got: BTreeSet<(String, String)> =
        read.iter().map(|f| (f["manifest"].as_str().unwrap().to_string(), f["path"].as_str().unwrap().to_string())).collect();
    let mut want = BTreeSet::new();
    for m in [&rm, &dm] {
        for f in m.files.iter().filter(|f| !f.optional) {
            want.insert((m.name.clone(), f.path.clone()));
        }
    }
    assert_eq!(got, want);
    for f in read {
        assert!(f["sha256"].is_string(), "{f}");
        assert!(Path::new(f["local"].as_str().unwrap()).starts_with(&hub), "{f}");
    }
    assert_eq!(read.iter().filter(|f| f["tensors"].is_u64()).count(), 6, "one tensor list per module");
    // The model's identity: SHA-256 over `<module> <pin>` per loaded checkpoint, in load order
    // (the checked pins stand for the files' hashes).
    let lines: String = summary["weights"]["files"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| {
            let f = read.iter().find(|f| f["local"] == *p).unwrap_or_else(|| panic!("{p} not read through the manifest"));
            format!("{} {}\n", f["used_for"].as_str().unwrap(), f["sha256"].as_str().unwrap())
        })
        .collect();
    std::fs::write(root.join("identity-lines"), &lines).unwrap();
    let identity = &summary["model_identity"];
    assert_eq!(identity["sha256"], sha256_file(&root.join("identity-lines")).unwrap(), "{lines}");
    assert_eq!(summary["weights"]["sha256"], identity["sha256"]);
    assert_eq!(summary["recon_version"], env!("CARGO_PKG_VERSION"));
    let notes = summary["weights"]["notes"].to_string();
    for part in ["ss_flow: args from", "slat_flow: args from", "slat_dec_gs: args from", "slat_normalization", "samplers.slat"] {
        assert!(notes.contains(part), "{part}: {notes}");
    }
    assert!(stderr.contains("weights: 14 files of dinov2-vitl14-reg + recgen"), "{stderr}");

    // One byte of the stage-2 denoiser changed: the run stops on its SHA-256.
    let pt = hub.join("models--TRI-ML--RecGen/snapshots").join(COMMIT).join("slat_denoiser_ema0.9999_step0075000.pt");
    let blob = std::fs::canonicalize(&pt).unwrap();
    let good = std::fs::read(&blob).unwrap();
    let mut bad = good.clone();
    let mid = bad.len() - 9;
    bad[mid] ^= 0x40;
    std::fs::write(&blob, &bad).unwrap();
    let actual = sha256_file(&blob).unwrap();
    let pin = rm.files.iter().find(|f| f.path.ends_with("step0075000.pt")).and_then(|f| f.sha256.clone()).unwrap();
    let o = infer(&root, &manifest);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(err.contains("slat_denoiser_ema0.9999_step0075000.pt") && err.contains(&pin) && err.contains(&actual), "{err}");
    let o = recon_offline(&root, &["weights", "verify", hub.to_str().unwrap(), "--manifest", manifest.to_str().unwrap()]);
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stdout).contains("SHA-256 MISMATCH"));
    std::fs::write(&blob, &good).unwrap();

    // A file missing from the cache: offline, the error names the repo and the file.
    let cfg = hub.join("models--TRI-ML--RecGen/snapshots").join(COMMIT).join("ckpts/slat_dec_gs_swin8_B_64l8gs32_fp16.json");
    std::fs::remove_file(&cfg).unwrap();
    let o = infer(&root, &manifest);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(
        err.contains("ckpts/slat_dec_gs_swin8_B_64l8gs32_fp16.json") && err.contains("TRI-ML/RecGen") && err.contains("HF_HUB_OFFLINE"),
        "{err}"
    );
    let _ = std::fs::remove_dir_all(&root);
}
