//! Checkpoint loading and validation on locally made files: random-init
//! safetensors, damaged copies (missing / extra / wrong-shape tensors),
//! f16/bf16 conversions, torch-format `.pt` files (made without torch by
//! tests/fixtures/weights/make_pt.py), manifest verification and offline fetch.

use candle_core::{DType, Device, Tensor};
use recon::model::{Dinov2, Dinov2Config, ModuleArgs};
use recon::weights::Manifest;
use recon::weights::{expected_tensors, ModuleConfig};
use recon::weights::{is_random_init, print_table, validate_checkpoint, verify_dir, write_random_init};
use recon::weights::{mmaped_safetensors_vb, Checkpoint};
use recon::Error;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

use recon_testkit::{repo as root, tmp};

fn tiny_cfg() -> (Dinov2Config, Vec<recon::weights::TensorSpec>) {
    let spec = ModuleConfig::read(&root().join("models/dinov2_tiny.json")).unwrap();
    let args = ModuleArgs::from_spec(&spec, "dinov2_tiny.json").unwrap();
    let specs = expected_tensors(&args, "dinov2_tiny.json").unwrap();
    (args.dinov2("dinov2_tiny.json").unwrap().clone(), specs)
}

/// Random-init tiny DINOv2 weights in `dir`; returns (path, tensors).
fn make_init(dir: &Path, seed: u64) -> (PathBuf, HashMap<String, Tensor>) {
    let p = write_random_init(&root().join("models/dinov2_tiny.json"), dir, seed).unwrap();
    let t = candle_core::safetensors::load(&p, &Device::Cpu).unwrap();
    (p, t)
}

fn save(t: &HashMap<String, Tensor>, p: &Path) {
    candle_core::safetensors::save(t, p).unwrap();
}

fn forward(vb: candle_nn::VarBuilder) -> Tensor {
    let cfg = tiny_cfg().0;
    let m = Dinov2::new(&cfg, vb, recon::model::Compute::Plain).unwrap();
    let x = Tensor::arange(0f32, (3 * 56 * 56) as f32, &Device::Cpu).unwrap().reshape((1, 3, 56, 56)).unwrap();
    let x = (x / 5000.0).unwrap().sin().unwrap();
    m.forward(&x).unwrap().x_prenorm
}

#[test]
fn random_init_is_labelled_deterministic_and_valid() {
    let d = tmp("init");
    let (p, t) = make_init(&d, 3);
    assert!(is_random_init(&p).unwrap());
    let (_, specs) = tiny_cfg();
    assert_eq!(t.len(), specs.len());
    let ck = Checkpoint::open(&p, None).unwrap();
    let rep = validate_checkpoint(&ck, &specs, false).unwrap();
    assert_eq!(rep.matched, specs.len());
    // Same seed → identical bytes; other seed → different.
    let d2 = tmp("init2");
    let (p2, _) = make_init(&d2, 3);
    assert_eq!(std::fs::read(&p).unwrap(), std::fs::read(&p2).unwrap());
    let (p3, _) = make_init(&tmp("init3"), 4);
    assert_ne!(std::fs::read(&p).unwrap(), std::fs::read(&p3).unwrap());
    // A trained-looking file is not labelled.
    let plain = d.join("plain.safetensors");
    save(&t, &plain);
    assert!(!is_random_init(&plain).unwrap());
    // The config copy next to the weights builds the same module.
    assert!(d.join("dinov2_tiny.json").exists());
    // One-call validated load.
    let vb = recon::weights::load_validated(&p, &specs, false, DType::F32, &Device::Cpu).unwrap();
    let a = forward(vb);
    assert!(recon::weights::load_validated(&p, &specs[1..], false, DType::F32, &Device::Cpu).is_err());
    let b = forward(Checkpoint::open(&p2, None).unwrap().into_var_builder(DType::F32, &Device::Cpu));
    assert_eq!(recon::util::max_abs_diff(&a, &b).unwrap(), 0.0);
}

/// `recon weights init --format pt`: the same tensors as a torch archive (the released
/// denoisers' format), labelled by an extra record; the plain `write_pt` is not labelled.
#[test]
fn random_init_as_torch_archive() {
    let d = tmp("init-pt");
    let cfg = root().join("models/dinov2_tiny.json");
    let p = recon::weights::write_random_init_as(&cfg, &d, 3, recon::weights::InitFormat::Pt).unwrap();
    assert_eq!(p, d.join("dinov2_tiny.pt"));
    assert!(is_random_init(&p).unwrap());
    let (sp, st) = make_init(&tmp("init-pt-st"), 3);
    let (_, specs) = tiny_cfg();
    let ck = Checkpoint::open(&p, None).unwrap();
    assert_eq!(validate_checkpoint(&ck, &specs, false).unwrap().matched, specs.len());
    let a = forward(ck.into_var_builder(DType::F32, &Device::Cpu));
    let b = forward(Checkpoint::open(&sp, None).unwrap().into_var_builder(DType::F32, &Device::Cpu));
    assert_eq!(recon::util::max_abs_diff(&a, &b).unwrap(), 0.0, "same seed, same weights in either format");
    let plain = d.join("plain.pt");
    recon::weights::write_pt(&st.into_iter().collect(), &plain).unwrap();
    assert!(!is_random_init(&plain).unwrap());
}

#[test]
fn missing_extra_and_wrong_shape_are_named() {
    let d = tmp("damage");
    let (_, t) = make_init(&d, 1);
    let (_, specs) = tiny_cfg();

    let mut missing = t.clone();
    missing.remove("blocks.1.mlp.fc2.weight").unwrap();
    let p = d.join("missing.safetensors");
    save(&missing, &p);
    match validate_checkpoint(&Checkpoint::open(&p, None).unwrap(), &specs, false) {
        Err(Error::MissingTensor { name, expected, .. }) => {
            assert_eq!(name, "blocks.1.mlp.fc2.weight");
            assert_eq!(expected, vec![64, 256]);
        }
        other => panic!("expected MissingTensor, got {other:?}"),
    }

    let mut extra = t.clone();
    extra.insert("head.weight".into(), Tensor::zeros((3, 64), DType::F32, &Device::Cpu).unwrap());
    let p = d.join("extra.safetensors");
    save(&extra, &p);
    let ck = Checkpoint::open(&p, None).unwrap();
    match validate_checkpoint(&ck, &specs, false) {
        Err(Error::UnexpectedTensors { names, .. }) => assert_eq!(names, vec!["head.weight".to_string()]),
        other => panic!("expected UnexpectedTensors, got {other:?}"),
    }
    // strict=False semantics tolerate extras only.
    assert!(validate_checkpoint(&ck, &specs, true).is_ok());

    let mut wrong = t.clone();
    wrong.insert("pos_embed".into(), Tensor::zeros((1, 10, 64), DType::F32, &Device::Cpu).unwrap());
    let p = d.join("wrong.safetensors");
    save(&wrong, &p);
    let err = validate_checkpoint(&Checkpoint::open(&p, None).unwrap(), &specs, false).unwrap_err();
    match &err {
        Error::ShapeMismatch { name, found, expected, .. } => {
            assert_eq!(name, "pos_embed");
            assert_eq!(found, &vec![1, 10, 64]);
            assert_eq!(expected, &vec![1, 17, 64]);
        }
        other => panic!("expected ShapeMismatch, got {other:?}"),
    }
    let msg = err.to_string();
    assert!(msg.contains("pos_embed") && msg.contains("[1, 10, 64]") && msg.contains("[1, 17, 64]"), "{msg}");
    // Building the model straight from the bad file fails too (shape-checked backend).
    let vb = Checkpoint::open(&p, None).unwrap().into_var_builder(DType::F32, &Device::Cpu);
    let cfg = tiny_cfg().0;
    assert!(Dinov2::new(&cfg, vb, recon::model::Compute::Plain).is_err());
}

#[test]
fn half_precision_files_load_as_f32() {
    let d = tmp("half");
    let (p32, t) = make_init(&d, 5);
    let reference = forward(Checkpoint::open(&p32, None).unwrap().into_var_builder(DType::F32, &Device::Cpu));
    // candle's own mmap backend agrees with ours.
    let via_mmap = forward(mmaped_safetensors_vb(std::slice::from_ref(&p32), DType::F32, &Device::Cpu).unwrap());
    assert_eq!(recon::util::max_abs_diff(&reference, &via_mmap).unwrap(), 0.0);
    for (dt, tol) in [(DType::F16, 2e-2), (DType::BF16, 1e-1)] {
        let half: HashMap<String, Tensor> = t.iter().map(|(k, v)| (k.clone(), v.to_dtype(dt).unwrap())).collect();
        let p = d.join(format!("{dt:?}.safetensors"));
        save(&half, &p);
        let ck = Checkpoint::open(&p, None).unwrap();
        assert!(ck.tensors().values().all(|s| s.dtype == dt));
        let vb = ck.into_var_builder(DType::F32, &Device::Cpu);
        assert_eq!(vb.get((1, 17, 64), "pos_embed").unwrap().dtype(), DType::F32);
        let out = forward(vb);
        let err = recon::util::max_abs_diff(&out, &reference).unwrap();
        assert!(err < tol && err > 0.0, "{dt:?}: max abs {err}");
    }
}

#[test]
fn torch_pt_files_plain_and_wrapped() {
    let dir = root().join("tests/fixtures/weights");
    let plain = Checkpoint::open(&dir.join("plain.pt"), None).unwrap();
    assert_eq!(plain.pt_key, None);
    assert_eq!(plain.stripped_prefix, "");
    let vb = plain.into_var_builder(DType::F32, &Device::Cpu);
    assert_eq!(vb.get((2, 3), "a").unwrap().to_vec2::<f32>().unwrap(), vec![vec![1., 2., 3.], vec![4., 5., 6.]]);
    assert_eq!(vb.get(2, "b").unwrap().to_vec1::<f32>().unwrap(), vec![0.5, -1.5]);
    assert!(vb.get((3, 2), "a").is_err());

    // {"step": 7, "state_dict": {"module.a": f16, "module.b": bf16}}
    let wrapped = Checkpoint::open(&dir.join("wrapped.pt"), None).unwrap();
    assert_eq!(wrapped.pt_key.as_deref(), Some("state_dict"));
    assert_eq!(wrapped.stripped_prefix, "module.");
    let names: Vec<String> = wrapped.tensors().keys().cloned().collect();
    assert_eq!(names, vec!["a".to_string(), "b".to_string()]);
    assert_eq!(wrapped.tensors()["a"].dtype, DType::F16);
    assert_eq!(wrapped.tensors()["b"].dtype, DType::BF16);
    let specs = vec![
        recon::weights::TensorSpec { name: "a".into(), shape: vec![2, 3] },
        recon::weights::TensorSpec { name: "b".into(), shape: vec![2] },
    ];
    validate_checkpoint(&wrapped, &specs, false).unwrap();
    let vb = wrapped.into_var_builder(DType::F32, &Device::Cpu);
    assert_eq!(vb.get((2, 3), "a").unwrap().to_vec2::<f32>().unwrap(), vec![vec![1., 2., 3.], vec![4., 5., 6.]]);
    assert_eq!(vb.get(2, "b").unwrap().to_vec1::<f32>().unwrap(), vec![0.5, -1.5]);

    assert!(Checkpoint::open(&dir.join("wrapped.pt"), Some("nope")).is_err());
    assert!(Checkpoint::open(&dir.join("absent.pt"), None).is_err());
}

#[test]
fn verify_table_on_a_directory() {
    let d = tmp("verify");
    let (p, _) = make_init(&d, 2);
    let (_, specs) = tiny_cfg();
    let m = Manifest {
        name: "tiny".into(),
        source: "huggingface".into(),
        repo: Some("org/tiny".into()),
        revision: Some("main".into()),
        licence: None,
        notes: vec![],
        requires: vec![],
        files: vec![
            serde_json::from_value(
                serde_json::json!({"path": p.file_name().unwrap().to_str().unwrap(), "kind": "safetensors", "tensors": specs}),
            )
            .unwrap(),
            serde_json::from_value(serde_json::json!({"path": "dinov2_tiny.json", "kind": "json"})).unwrap(),
            serde_json::from_value(serde_json::json!({"path": "absent.safetensors", "kind": "safetensors", "tensors_note": "x"})).unwrap(),
        ],
    };
    let rows = verify_dir(&m, &d).unwrap();
    assert!(rows[0].ok && rows[0].tensors == Some((specs.len(), specs.len())), "{:?}", rows[0]);
    assert!(rows[1].ok);
    assert!(!rows[2].ok && !rows[2].present);
    let mut out = Vec::new();
    print_table(&m, &d, &rows, &mut out);
    let s = String::from_utf8(out).unwrap();
    assert!(s.contains("MISSING") && s.contains("OK"), "{s}");
}

#[test]
fn fetch_without_network_names_repo_and_file() {
    // Point the client at a closed local port so the test never touches the network
    // (HF_ENDPOINT, through the settings as the CLI applies it).
    let mut s = recon::settings::current();
    s.hf_endpoint = Some("http://127.0.0.1:9".into());
    s.hf_offline = false;
    s.apply();
    let m = Manifest::load("recgen").unwrap();
    let cache = tmp("fetch");
    let err = recon::weights::fetch(&m, Some(&cache), false).unwrap_err().to_string();
    assert!(err.contains("TRI-ML/RecGen") && err.contains("pipeline.json"), "{err}");
}
