//! Resource bounds before allocation: inputs whose headers claim enormous
//! sizes get a typed error naming the file and the field, never an abort.
//! Each file here is a few hundred bytes that claims terabytes.

mod common;

use common::{recon, tmp};
use recon::weights::Checkpoint;
use recon::Error;
use std::io::Write;

fn refused<T>(r: recon::Result<T>) -> Error {
    match r {
        Ok(_) => panic!("accepted an input it should refuse"),
        Err(e) => e,
    }
}

fn too_large(e: &Error) -> (&str, &str, u128, u128) {
    match e {
        Error::TooLarge(b) => (b.file.as_str(), b.field.as_str(), b.claimed, b.limit),
        other => panic!("expected a TooLarge error, got: {other}"),
    }
}

#[test]
fn safetensors_header_claiming_a_trillion_elements() {
    let dir = tmp("bound-st");
    let p = dir.join("big.safetensors");
    // 10^12 f32 elements (4 TB) in a 100-byte file.
    let mut h = br#"{"w":{"dtype":"F32","shape":[1000000,1000000],"data_offsets":[0,4000000000000]}}"#.to_vec();
    h.resize(h.len().div_ceil(8) * 8, b' ');
    let mut f = std::fs::File::create(&p).unwrap();
    f.write_all(&(h.len() as u64).to_le_bytes()).unwrap();
    f.write_all(&h).unwrap();
    f.write_all(&[0u8; 16]).unwrap();
    drop(f);
    let e = refused(Checkpoint::open(&p, None));
    let (file, field, claimed, limit) = too_large(&e);
    assert!(file.ends_with("big.safetensors"), "{e}");
    assert_eq!(field, "tensor `w` shape", "{e}");
    assert_eq!((claimed, limit), (4_000_000_000_000, 16));
    // The header length itself is bounded by the file.
    let p2 = dir.join("len.safetensors");
    std::fs::write(&p2, [u64::MAX.to_le_bytes().as_slice(), b"{}"].concat()).unwrap();
    let e = refused(Checkpoint::open(&p2, None));
    assert_eq!(too_large(&e).1, "header length", "{e}");
}

/// A minimal torch archive whose one tensor claims 10^6 × 10^6 floats over a 24-byte storage.
fn huge_pt(path: &std::path::Path) {
    let mut pkl = b"\x80\x02}q\x00(X\x01\x00\x00\x00actorch._utils\n_rebuild_tensor_v2\n((X\x07\x00\x00\x00storagectorch\nFloatStorage\nX\x01\x00\x00\x000X\x03\x00\x00\x00cpuK\x06tQK\x00".to_vec();
    pkl.extend_from_slice(b"(J\x40\x42\x0f\x00J\x40\x42\x0f\x00t(J\x40\x42\x0f\x00K\x01t\x89ccollections\nOrderedDict\n)RtRu.");
    let f = std::fs::File::create(path).unwrap();
    let mut z = zip::ZipWriter::new(f);
    let o = zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
    z.start_file("archive/data.pkl", o).unwrap();
    z.write_all(&pkl).unwrap();
    z.start_file("archive/data/0", o).unwrap();
    z.write_all(&[0u8; 24]).unwrap();
    z.finish().unwrap();
}

#[test]
fn pt_tensor_claiming_a_trillion_elements() {
    let dir = tmp("bound-pt");
    let p = dir.join("big.pt");
    huge_pt(&p);
    let e = refused(Checkpoint::open(&p, None));
    let (file, field, claimed, limit) = too_large(&e);
    assert!(file.ends_with("big.pt"), "{e}");
    assert!(field.starts_with("tensor `a` shape [1000000, 1000000]"), "{e}");
    assert_eq!((claimed, limit), (4_000_000_000_000, 24));
}

/// A PNG whose header says 100 000 × 100 000 (IHDR only; the decoder never gets further).
fn huge_png(path: &std::path::Path, w: u32, h: u32) {
    fn chunk(out: &mut Vec<u8>, ty: &[u8], data: &[u8]) {
        out.extend_from_slice(&(data.len() as u32).to_be_bytes());
        let mut c = ty.to_vec();
        c.extend_from_slice(data);
        out.extend_from_slice(&c);
        out.extend_from_slice(&crc32(&c).to_be_bytes());
    }
    fn crc32(b: &[u8]) -> u32 {
        let mut c = 0xffff_ffffu32;
        for &x in b {
            c ^= x as u32;
            for _ in 0..8 {
                c = if c & 1 != 0 { 0xedb8_8320 ^ (c >> 1) } else { c >> 1 };
            }
        }
        !c
    }
    let mut png = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut ihdr = Vec::new();
    ihdr.extend_from_slice(&w.to_be_bytes());
    ihdr.extend_from_slice(&h.to_be_bytes());
    ihdr.extend_from_slice(&[8, 2, 0, 0, 0]); // 8-bit RGB
    chunk(&mut png, b"IHDR", &ihdr);
    chunk(&mut png, b"IDAT", &[0x78, 0x9c, 0x03, 0x00, 0x00, 0x00, 0x00, 0x01]);
    chunk(&mut png, b"IEND", &[]);
    std::fs::write(path, png).unwrap();
}

#[test]
fn image_of_100000_by_100000_pixels() {
    let dir = tmp("bound-png");
    let p = dir.join("big-color.png");
    huge_png(&p, 100_000, 100_000);
    let e = refused(recon::dataset::RgbdFrame::open(&p, &recon::dataset::FrameOptions::default()));
    let (file, field, claimed, limit) = too_large(&e);
    assert!(file.ends_with("big-color.png"), "{e}");
    assert_eq!((field, claimed, limit), ("image width/height", 100_000, recon::util::MAX_IMAGE_SIDE as u128));
    // Within the side bound but over the pixel bound.
    let p2 = dir.join("wide-label.png");
    huge_png(&p2, 30_000, 30_000);
    let e = refused(recon::dataset::InstanceMap::open(&p2));
    assert_eq!(too_large(&e).1, "image size", "{e}");
    // The CLI says the same, and exits with an error instead of aborting.
    let out = recon(&["infer", "--rgbd", p.to_str().unwrap(), "--masks", p2.to_str().unwrap(), "--weights", "random"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(err.contains("big-color.png") && err.contains("100000") && err.contains("limit"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
}

#[test]
fn ply_claiming_a_billion_vertices() {
    let dir = tmp("bound-ply");
    let p = dir.join("big.ply");
    let mut b =
        b"ply\nformat binary_little_endian 1.0\nelement vertex 1000000000\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
            .to_vec();
    b.extend_from_slice(&[0u8; 36]);
    std::fs::write(&p, b).unwrap();
    let e = refused(recon::dataset::read_ply(&p));
    let (file, field, claimed, limit) = too_large(&e);
    assert!(file.ends_with("big.ply"), "{e}");
    assert_eq!((field, claimed, limit), ("element `vertex` count", 1_000_000_000, 3));
    // ASCII: one byte per value at least.
    let p = dir.join("big_ascii.ply");
    std::fs::write(
        &p,
        "ply\nformat ascii 1.0\nelement vertex 1000000000\nproperty float x\nproperty float y\nproperty float z\nend_header\n0 0 0\n",
    )
    .unwrap();
    let e = refused(recon::dataset::read_ply(&p));
    assert_eq!(too_large(&e).2, 1_000_000_000, "{e}");
    // An element without properties and a huge count is skipped, not looped over.
    let p = dir.join("empty_elem.ply");
    std::fs::write(
        &p,
        "ply\nformat ascii 1.0\nelement junk 18446744073709551615\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 3\n",
    )
    .unwrap();
    assert_eq!(recon::dataset::read_ply(&p).unwrap().vertices, vec![[1.0, 2.0, 3.0]]);
}

#[test]
fn mat_zlib_bomb_is_refused() {
    use flate2::write::ZlibEncoder;
    // A miCOMPRESSED element whose stream inflates to 65 MiB of zeros (65 KB compressed).
    let mut enc = ZlibEncoder::new(Vec::new(), flate2::Compression::best());
    let zeros = vec![0u8; 1 << 20];
    for _ in 0..65 {
        enc.write_all(&zeros).unwrap();
    }
    let z = enc.finish().unwrap();
    let mut buf = b"MATLAB 5.0 MAT-file, recon bounds test".to_vec();
    buf.resize(116, b' ');
    buf.extend_from_slice(&[0u8; 8]);
    buf.extend_from_slice(&0x0100u16.to_le_bytes());
    buf.extend_from_slice(b"IM");
    buf.extend_from_slice(&15u32.to_le_bytes());
    buf.extend_from_slice(&(z.len() as u32).to_le_bytes());
    buf.extend_from_slice(&z);
    let e = refused(recon::dataset::MatFile::parse(&buf, "bomb.mat"));
    let (file, _, claimed, limit) = too_large(&e);
    assert_eq!(file, "bomb.mat");
    assert_eq!(limit, recon::util::MAX_MAT_INFLATED as u128);
    assert!(claimed > limit, "{e}");
}

#[test]
fn architecture_larger_than_the_machine() {
    let dir = tmp("bound-arch");
    let mut v = common::read_json(&common::tiny_config());
    // A 4096³ stage-1 grid: 4096³ tokens × 64 channels × 5 × 4 bytes ≈ 88 TB at least.
    v["ss_flow"]["args"]["resolution"] = 4096.into();
    let p = dir.join("huge.json");
    std::fs::write(&p, serde_json::to_string(&v).unwrap()).unwrap();
    let e = refused(recon::model::RecGenConfig::load(&p));
    let (file, field, claimed, limit) = too_large(&e);
    assert!(file.ends_with("huge.json"), "{e}");
    // Both the flow's tokens and the decoder's finest grid (16384³ × 8 × 4 B) grow with it; the larger is named.
    assert!(field.contains("ss_flow.args.resolution"), "{e}");
    assert!(claimed > 80_000_000_000_000 && limit < claimed, "{e}");
    // A cluster job's share: RECON_MEMORY_LIMIT_MB lowers the bound, so the
    // large architecture (≥ 0.6 GB of one flow's weights) is refused at 100 MB.
    let large = common::repo().join("models/recgen-large.json");
    let out = common::recon_with_env(
        &[
            "infer",
            "--rgbd",
            "data/sample/000001-color.png",
            "--masks",
            "data/sample/000001-label.png",
            "--weights",
            "random",
            "--config",
            large.to_str().unwrap(),
        ],
        &[("RECON_MEMORY_LIMIT_MB", std::path::Path::new("100"))],
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(err.contains("recgen-large.json") && err.contains("weights") && err.contains("limit of 104857600"), "{err}");
}
