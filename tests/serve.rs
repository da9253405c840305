//! `recon serve` over HTTP on 127.0.0.1 (port 0), against the `recon` binary: the README
//! sample byte for byte against `recon infer`, bad requests, load, kill -9 and restart,
//! SIGTERM, a client that disconnects, auth, path traversal, the OpenAPI document.
//! Plumbing tests run the random tiny model with one sampler step on one object.
mod common;

use common::{repo, tmp};
use std::io::{Read, Write};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// A `recon serve` process.
struct Server {
    child: Child,
    addr: SocketAddr,
    log: PathBuf,
}

impl Server {
    /// Starts `recon serve --bind 127.0.0.1:0 --data-dir <data>` with `args`, from `cwd`.
    fn start(data: &Path, cwd: &Path, args: &[&str], env: &[(&str, &str)]) -> Server {
        let log = data.with_extension(format!("{}.log", std::process::id()));
        let mut c = Command::new(env!("CARGO_BIN_EXE_recon"));
        c.args(["serve", "--bind", "127.0.0.1:0", "--data-dir", data.to_str().unwrap()])
            .args(args)
            .current_dir(cwd)
            .stdout(Stdio::piped())
            .stderr(std::fs::OpenOptions::new().create(true).append(true).open(&log).unwrap());
        for (k, v) in env {
            c.env(k, v);
        }
        let mut child = c.spawn().expect("starting recon serve");
        let mut out = child.stdout.take().unwrap();
        let mut line = Vec::new();
        let mut b = [0u8; 1];
        while out.read(&mut b).unwrap_or(0) == 1 && b[0] != b'\n' {
            line.push(b[0]);
        }
        let line = String::from_utf8_lossy(&line).to_string();
        let Some(addr) = line.strip_prefix("recon serve: listening on http://") else {
            let _ = child.kill();
            panic!("recon serve did not start: {line:?}\n{}", std::fs::read_to_string(&log).unwrap_or_default());
        };
        Server { addr: addr.trim().parse().unwrap(), child, log }
    }

    /// The tiny random model, one sampler step by default.
    fn tiny(data: &Path, extra: &[&str]) -> Server {
        let mut a = vec!["--weights", "random", "--config", "models/recgen-tiny.json", "--steps", "1"];
        a.extend_from_slice(extra);
        Server::start(data, &repo(), &a, &[])
    }

    fn url(&self, path: &str) -> String {
        format!("http://{}{path}", self.addr)
    }

    fn logs(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    fn kill9(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// An HTTP answer.
struct Answer {
    status: u16,
    headers: Vec<(String, String)>,
    body: Vec<u8>,
}

impl Answer {
    fn json(&self) -> serde_json::Value {
        serde_json::from_slice(&self.body).unwrap_or_else(|e| panic!("{e}: {}", String::from_utf8_lossy(&self.body)))
    }
    fn header(&self, k: &str) -> Option<&str> {
        self.headers.iter().find(|(n, _)| n.eq_ignore_ascii_case(k)).map(|(_, v)| v.as_str())
    }
    fn text(&self) -> String {
        String::from_utf8_lossy(&self.body).to_string()
    }
}

fn request(method: &str, url: &str, body: Option<(&str, &[u8])>, token: Option<&str>) -> Answer {
    let agent = ureq::AgentBuilder::new().timeout(Duration::from_secs(600)).build();
    let mut r = agent.request(method, url);
    if let Some(t) = token {
        r = r.set("Authorization", &format!("Bearer {t}"));
    }
    let res = match body {
        Some((ct, b)) => r.set("Content-Type", ct).send_bytes(b),
        None => r.call(),
    };
    let resp = match res {
        Ok(r) => r,
        Err(ureq::Error::Status(_, r)) => r,
        Err(e) => panic!("{method} {url}: {e}"),
    };
    let status = resp.status();
    let headers = resp.headers_names().into_iter().map(|n| (n.clone(), resp.header(&n).unwrap_or("").to_string())).collect();
    let mut body = Vec::new();
    resp.into_reader().take(1 << 30).read_to_end(&mut body).unwrap();
    Answer { status, headers, body }
}

fn get(url: &str) -> Answer {
    request("GET", url, None, None)
}

/// A multipart body: `(name, filename, bytes)` parts.
fn multipart(parts: &[(&str, Option<&str>, &[u8])]) -> (String, Vec<u8>) {
    let boundary = "----recon-test-boundary-7f3a";
    let mut b = Vec::new();
    for (name, filename, bytes) in parts {
        write!(b, "--{boundary}\r\nContent-Disposition: form-data; name=\"{name}\"").unwrap();
        if let Some(f) = filename {
            write!(b, "; filename=\"{f}\"").unwrap();
        }
        b.extend_from_slice(b"\r\nContent-Type: application/octet-stream\r\n\r\n");
        b.extend_from_slice(bytes);
        b.extend_from_slice(b"\r\n");
    }
    write!(b, "--{boundary}--\r\n").unwrap();
    (format!("multipart/form-data; boundary={boundary}"), b)
}

fn post_parts(s: &Server, query: &str, parts: &[(&str, Option<&str>, &[u8])]) -> Answer {
    let (ct, body) = multipart(parts);
    request("POST", &s.url(&format!("/v1/reconstruct{query}")), Some((&ct, &body)), None)
}

/// A raw HTTP/1.1 exchange (for what clients refuse to send): the status and the
/// answer. The request is written from a thread of its own while the answer is read, so
/// an answer the server sends before reading everything (413, 401) is still seen.
fn raw(addr: SocketAddr, bytes: &[u8]) -> (u16, String) {
    let c = std::net::TcpStream::connect(addr).unwrap();
    c.set_read_timeout(Some(Duration::from_secs(120))).unwrap();
    let mut w = c.try_clone().unwrap();
    let bytes = bytes.to_vec();
    let writer = std::thread::spawn(move || {
        for chunk in bytes.chunks(64 << 10) {
            if w.write_all(chunk).is_err() {
                break;
            }
        }
    });
    let mut out = Vec::new();
    let mut buf = [0u8; 8192];
    let mut r = &c;
    while let Ok(n) = r.read(&mut buf) {
        if n == 0 {
            break;
        }
        out.extend_from_slice(&buf[..n]);
    }
    let _ = c.shutdown(std::net::Shutdown::Both);
    let _ = writer.join();
    let text = String::from_utf8_lossy(&out).to_string();
    let status = text.split_whitespace().nth(1).and_then(|s| s.parse().ok()).unwrap_or(0);
    (status, text)
}

/// A chunked POST of `body` to `path`, raw.
fn raw_chunked(addr: SocketAddr, path: &str, content_type: &str, body: &[u8]) -> (u16, String) {
    let mut b = format!(
        "POST {path} HTTP/1.1\r\nHost: x\r\nContent-Type: {content_type}\r\nTransfer-Encoding: chunked\r\nConnection: close\r\n\r\n"
    )
    .into_bytes();
    for c in body.chunks(32 << 10) {
        b.extend(format!("{:x}\r\n", c.len()).as_bytes());
        b.extend_from_slice(c);
        b.extend_from_slice(b"\r\n");
    }
    b.extend_from_slice(b"0\r\n\r\n");
    raw(addr, &b)
}

/// The shipped sample: colour, depth and label PNGs, and the intrinsics JSON (K and the
/// depth scale of its meta.mat).
struct Sample {
    rgb: Vec<u8>,
    depth: Vec<u8>,
    label: Vec<u8>,
    intrinsics: Vec<u8>,
}

fn sample() -> Sample {
    let d = repo().join("data/sample");
    let mat = std::fs::read(d.join("000001-meta.mat")).unwrap();
    let (k, scale) = recon::dataset::frame::intrinsics_from_bytes(&mat, recon::dataset::frame::CameraFormat::Mat, "meta").unwrap();
    let intr = serde_json::json!({"fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy, "depth_scale_m": scale.unwrap()});
    Sample {
        rgb: std::fs::read(d.join("000001-color.png")).unwrap(),
        depth: std::fs::read(d.join("000001-depth.png")).unwrap(),
        label: std::fs::read(d.join("000001-label.png")).unwrap(),
        intrinsics: intr.to_string().into_bytes(),
    }
}

/// The sample's parts with `options` (JSON) and one object (id 8) for the tiny plumbing runs.
fn tiny_parts<'a>(s: &'a Sample, options: &'a [u8]) -> Vec<(&'static str, Option<&'static str>, &'a [u8])> {
    vec![
        ("rgb", Some("000001-color.png"), &s.rgb),
        ("depth", Some("000001-depth.png"), &s.depth),
        ("masks", Some("000001-label.png"), &s.label),
        ("intrinsics", None, &s.intrinsics),
        ("objects", None, b"8"),
        ("options", None, options),
    ]
}

const FAST: &[u8] = br#"{"max_faces": 20000}"#;

fn wait_status(s: &Server, id: &str, want: &[&str], secs: u64) -> serde_json::Value {
    let t0 = Instant::now();
    loop {
        let j = get(&s.url(&format!("/v1/jobs/{id}"))).json();
        if want.contains(&j["status"].as_str().unwrap_or("")) {
            return j;
        }
        assert!(t0.elapsed() < Duration::from_secs(secs), "job {id} still {} after {secs} s\n{}", j["status"], s.logs());
        std::thread::sleep(Duration::from_millis(50));
    }
}

fn error_of(a: &Answer) -> (u16, String, String, String) {
    let j = a.json();
    let e = &j["error"];
    (
        a.status,
        e["part"].as_str().unwrap_or("").into(),
        e["field"].as_str().unwrap_or("").into(),
        e["message"].as_str().unwrap_or("").into(),
    )
}

/// Files of a zip: name → bytes.
fn unzip(bytes: &[u8]) -> std::collections::BTreeMap<String, Vec<u8>> {
    let mut z = zip::ZipArchive::new(std::io::Cursor::new(bytes)).unwrap();
    (0..z.len())
        .map(|i| {
            let mut f = z.by_index(i).unwrap();
            let mut b = Vec::new();
            f.read_to_end(&mut b).unwrap();
            (f.name().unwrap().to_string(), b)
        })
        .collect()
}

/// A JSON file without its timing fields (they differ between any two runs).
fn without_timings(bytes: &[u8]) -> serde_json::Value {
    fn strip(v: &mut serde_json::Value) {
        match v {
            serde_json::Value::Object(m) => {
                for k in ["timings_s", "postprocess_s", "select_s", "stage_seconds", "preprocess_s"] {
                    m.remove(k);
                }
                m.values_mut().for_each(strip);
            }
            serde_json::Value::Array(a) => a.iter_mut().for_each(strip),
            _ => {}
        }
    }
    let mut v: serde_json::Value = serde_json::from_slice(bytes).unwrap();
    strip(&mut v);
    v
}

/// The README sample over HTTP with the shipped default model and default options (one
/// object, id 21, on both sides) gives the files `recon infer` writes with the same
/// options, byte for byte (JSON: but for
/// the timing fields). The CLI writes into the server's output path, so the paths the
/// index records agree too.
#[test]
fn readme_sample_over_http_matches_recon_infer() {
    let t = tmp("serve-readme");
    let s = sample();
    for (name, bytes) in
        [("000001-color.png", &s.rgb), ("000001-depth.png", &s.depth), ("000001-label.png", &s.label), ("K.json", &s.intrinsics)]
    {
        std::fs::write(t.join(name), bytes).unwrap();
    }
    let cache = t.join("cache");
    let env = [("RECON_CACHE", cache.to_str().unwrap())];
    let server = Server::start(&t.join("data"), &t, &[], &env);
    // One object of the three (id 21: its mesh is the one the face budget decimates), to
    // keep the test's time small; every option is the default.
    let parts = [
        ("rgb", Some("000001-color.png"), &s.rgb[..]),
        ("depth", Some("000001-depth.png"), &s.depth[..]),
        ("masks", Some("000001-label.png"), &s.label[..]),
        ("intrinsics", Some("K.json"), &s.intrinsics[..]),
        ("objects", None, &b"21"[..]),
    ];
    let t0 = Instant::now();
    let a = post_parts(&server, "", &parts);
    let http_s = t0.elapsed().as_secs_f64();
    assert_eq!(a.status, 200, "{}\n{}", a.text(), server.logs());
    let job = a.json();
    let id = job["id"].as_str().unwrap().to_string();
    // The answer names the recon and the model (the pose files' identity, compared below).
    assert_eq!(job["result"]["recon_version"], env!("CARGO_PKG_VERSION"));
    let identity = &job["result"]["model_identity"];
    assert_eq!(identity["name"], "recgen-nano");
    assert_eq!(identity["sha256"].as_str().map(str::len), Some(64), "{identity}");
    let objects = job["result"]["objects"].as_array().unwrap();
    assert_eq!(objects.iter().filter(|o| o["status"] == "ok").count(), 1, "{job:#}");
    for o in objects.iter().filter(|o| o["status"] == "ok") {
        let p = &o["pose"];
        assert_eq!(p[3], serde_json::json!([0.0, 0.0, 0.0, 1.0]));
        let q: Vec<f64> = o["quaternion_xyzw"].as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect();
        assert!((q.iter().map(|x| x * x).sum::<f64>() - 1.0).abs() < 1e-4);
        assert!(o["scale"].as_f64().unwrap() > 0.0 && o["score"].is_number() && o["stage_seconds"]["total"].is_number());
        let glb = get(&server.url(o["files"]["mesh_glb"].as_str().unwrap()));
        assert_eq!((glb.status, &glb.body[..4]), (200, &b"glTF"[..]));
    }
    let zip = get(&server.url(&format!("/v1/jobs/{id}/archive")));
    assert_eq!((zip.status, zip.header("content-type")), (200, Some("application/zip")));
    let served = unzip(&zip.body);
    for (name, bytes) in &served {
        let f = get(&server.url(&format!("/v1/jobs/{id}/files/{name}")));
        assert!(f.status == 200 && &f.body == bytes, "{name}: the file route and the archive differ");
    }
    drop(server);

    // recon infer on the same files, written where the server wrote.
    let out = t.join("data/jobs").join(&id).join("out");
    let t0 = Instant::now();
    let o = Command::new(env!("CARGO_BIN_EXE_recon"))
        .args([
            "infer",
            "--rgbd",
            "000001-color.png",
            "--masks",
            "000001-label.png",
            "--depth",
            "000001-depth.png",
            "--intrinsics",
            "K.json",
            "--objects",
            "21",
        ])
        .arg("--out")
        .arg(&out)
        .current_dir(&t)
        .env("RECON_CACHE", &cache)
        .output()
        .unwrap();
    let cli_s = t0.elapsed().as_secs_f64();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    eprintln!("README sample: HTTP round trip {http_s:.2} s, recon infer process {cli_s:.2} s (model load included)");
    let cli = assert_same_files(&out, &served);
    let pose: serde_json::Value = serde_json::from_slice(&cli["id_21/pose.json"]).unwrap();
    assert_eq!((&pose["model_identity"], &pose["recon_version"]), (identity, &job["result"]["recon_version"]));
    let _ = std::fs::remove_dir_all(&t);
}

/// The files `recon infer` wrote under `out` against those the server `served` (by
/// relative path): the same names; JSON equal but for the timing fields, the rest byte
/// for byte. Returns the CLI's files.
fn assert_same_files(out: &Path, served: &std::collections::BTreeMap<String, Vec<u8>>) -> std::collections::BTreeMap<String, Vec<u8>> {
    let cli: std::collections::BTreeMap<String, Vec<u8>> =
        recon_testkit_files(out).into_iter().map(|n| (n.clone(), std::fs::read(out.join(&n)).unwrap())).collect();
    assert_eq!(cli.keys().collect::<Vec<_>>(), served.keys().collect::<Vec<_>>());
    for (name, bytes) in &cli {
        if name.ends_with(".json") {
            assert_eq!(without_timings(bytes), without_timings(&served[name]), "{name}");
        } else {
            assert!(bytes == &served[name], "{name} differs from recon infer's");
        }
    }
    cli
}

/// Every file under `root`, relative, sorted.
fn recon_testkit_files(root: &Path) -> Vec<String> {
    fn walk(d: &Path, p: &str, out: &mut Vec<String>) {
        for e in std::fs::read_dir(d).unwrap().flatten() {
            let n = e.file_name().to_string_lossy().to_string();
            let rel = if p.is_empty() { n } else { format!("{p}/{n}") };
            if e.file_type().unwrap().is_dir() {
                walk(&e.path(), &rel, out);
            } else {
                out.push(rel);
            }
        }
    }
    let mut v = Vec::new();
    walk(root, "", &mut v);
    v.sort();
    v
}

/// A PNG whose header claims `w`×`h` 8-bit grey pixels, with a few bytes of data: a
/// decompression bomb as far as any decoder that trusts the header is concerned.
fn png_claiming(w: u32, h: u32) -> Vec<u8> {
    let chunk = |kind: &[u8], data: &[u8]| {
        let mut c = (data.len() as u32).to_be_bytes().to_vec();
        let mut body = kind.to_vec();
        body.extend_from_slice(data);
        c.extend_from_slice(&body);
        c.extend_from_slice(&crc32(&body).to_be_bytes());
        c
    };
    let mut ihdr = w.to_be_bytes().to_vec();
    ihdr.extend(h.to_be_bytes());
    ihdr.extend([8, 0, 0, 0, 0]);
    let mut png = b"\x89PNG\r\n\x1a\n".to_vec();
    png.extend(chunk(b"IHDR", &ihdr));
    png.extend(chunk(b"IDAT", &[0x78, 0x9c, 0x63, 0x00, 0x00, 0x00, 0x01, 0x00, 0x01]));
    png.extend(chunk(b"IEND", &[]));
    png
}

fn crc32(b: &[u8]) -> u32 {
    let mut c = !0u32;
    for &x in b {
        c ^= x as u32;
        for _ in 0..8 {
            c = if c & 1 == 1 { 0xEDB8_8320 ^ (c >> 1) } else { c >> 1 };
        }
    }
    !c
}

fn png_gray(w: u32, h: u32, v: u8) -> Vec<u8> {
    let mut out = Vec::new();
    image::GrayImage::from_pixel(w, h, image::Luma([v])).write_to(&mut std::io::Cursor::new(&mut out), image::ImageFormat::Png).unwrap();
    out
}

/// Each bad request is a 4xx naming the part and the field, with the CLI's message
/// where the CLI refuses the same input; the server keeps serving.
#[test]
fn bad_requests_are_4xx_naming_part_and_field() {
    let t = tmp("serve-bad");
    let server = Server::tiny(&t.join("data"), &["--max-upload-mb", "8"]);
    let s = sample();
    let ok = tiny_parts(&s, FAST);
    let without = |name: &str| ok.iter().filter(|p| p.0 != name).cloned().collect::<Vec<_>>();
    let with = |name: &'static str, bytes: &'static [u8]| {
        let mut v = without(name);
        v.push((name, Some("x.png"), bytes));
        v
    };
    let leak = |b: Vec<u8>| -> &'static [u8] { Box::leak(b.into_boxed_slice()) };
    let mut tried = Vec::new();
    let mut check = |what: &str, parts: Vec<(&str, Option<&str>, &[u8])>, status: u16, part: &str, field: &str, msg: &str| {
        let a = post_parts(&server, "", &parts);
        let (st, p, f, m) = error_of(&a);
        assert_eq!((st, p.as_str(), f.as_str()), (status, part, field), "{what}: {m}");
        assert!(m.contains(msg), "{what}: `{m}` lacks `{msg}`");
        tried.push(format!("{what}: {st} part={p} field={f}: {m}"));
    };
    check("missing depth", without("depth"), 400, "depth", "depth", "missing part `depth`");
    check("missing masks", without("masks"), 400, "masks", "masks", "missing part `masks`");
    check("unknown part", with("colour", b"x"), 400, "colour", "name", "unknown part `colour`");
    check("text as rgb", with("rgb", b"hello"), 400, "rgb", "image", "rgb: cannot read colour image");
    check("8-bit depth", with("depth", leak(png_gray(640, 480, 7))), 400, "depth", "image", "depth must be a 16-bit single-channel PNG");
    check(
        "PNG bomb as rgb",
        with("rgb", leak(png_claiming(20_000, 20_000))),
        413,
        "rgb",
        "image size",
        "rgb: image size claims 400000000 pixels, more than the limit of 100000000",
    );
    check("PNG bomb as masks", with("masks", leak(png_claiming(40_000, 40_000))), 413, "masks", "image width/height", "claims 40000");
    check(
        "mask of the wrong size",
        with("masks", leak(png_gray(10, 10, 8))),
        400,
        "masks",
        "size",
        "mask is 10×10 but the frame is 640×480",
    );
    check("NaN focal (JSON)", with("intrinsics", br#"{"fx": NaN, "fy": 1, "cx": 1, "cy": 1}"#), 400, "intrinsics", "json", "invalid JSON");
    check("NaN focal (text)", with("intrinsics", b"NaN,500,320,240"), 400, "intrinsics", "fx", "need finite values and fx, fy > 0");
    check(
        "negative focal",
        with("intrinsics", br#"{"fx": -500, "fy": 500, "cx": 320, "cy": 240}"#),
        400,
        "intrinsics",
        "fx",
        "need finite values and fx, fy > 0",
    );
    check(
        "unknown option",
        with("options", br#"{"sampels": 2}"#),
        400,
        "options",
        "sampels",
        "unknown option `sampels`; the options are seed, samples,",
    );
    check("option out of range", with("options", br#"{"samples": 0}"#), 400, "options", "samples", "samples: must be at least 1, got 0");
    check("option of the wrong type", with("options", br#"{"samples": "two"}"#), 400, "options", "samples", "invalid type");
    let mut two = ok.clone();
    two.extend([
        ("rgb2", Some("b.png"), &s.rgb[..]),
        ("depth2", Some("b-depth.png"), &s.depth[..]),
        ("masks2", Some("b-label.png"), &s.label[..]),
        ("intrinsics2", None, &s.intrinsics[..]),
        ("T_c1_c2", None, &b"2,0,0,0, 0,2,0,0, 0,0,2,0, 0,0,0,1"[..]),
    ]);
    check("non-rigid T_c1_c2", two.clone(), 400, "T_c1_c2", "T_c1_c2", "T_c1_c2");
    two.retain(|p| p.0 != "depth2");
    check("second view without depth2", two, 400, "depth2", "depth2", "a second view needs rgb2, depth2");

    // Bodies no client library sends.
    let (ct, body) = multipart(&ok);
    let cut = &body[..body.len() / 2];
    let head = format!(
        "POST /v1/reconstruct HTTP/1.1\r\nHost: x\r\nContent-Type: {ct}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
        cut.len()
    );
    let (st, text) = raw(server.addr, &[head.as_bytes(), cut].concat());
    assert_eq!(st, 400, "truncated multipart: {text}");
    assert!(text.contains("malformed multipart body"), "{text}");
    tried.push(format!("truncated multipart: {st}"));
    let head = format!(
        "POST /v1/reconstruct HTTP/1.1\r\nHost: x\r\nContent-Type: {ct}\r\nContent-Length: 1000000000000\r\nConnection: close\r\n\r\n"
    );
    let (st, text) = raw(server.addr, head.as_bytes());
    assert!(st == 413 && text.contains("Content-Length"), "claimed length: {text}");
    tried.push(format!("Content-Length 10^12: {st}"));
    let big = vec![7u8; 9 << 20];
    let (ct_big, body_big) = multipart(&[("rgb", Some("a.png"), &big)]);
    let (st, text) = raw_chunked(server.addr, "/v1/reconstruct", &ct_big, &body_big);
    assert!(st == 413 && text.contains("--max-upload-mb"), "upload over --max-upload-mb, chunked: {text}");
    tried.push(format!("9 MiB chunked upload against --max-upload-mb 8: {st}"));
    let a = request("POST", &server.url("/v1/reconstruct"), Some(("application/json", b"{}")), None);
    assert_eq!(error_of(&a).0, 400, "{}", a.text());
    let a = post_parts(&server, "?wait=maybe", &ok);
    assert_eq!(error_of(&a).1, "wait");
    for line in &tried {
        eprintln!("{line}");
    }

    // Still serving: health, and the good request.
    assert_eq!(get(&server.url("/health")).status, 200);
    let a = post_parts(&server, "", &ok);
    assert_eq!(a.status, 200, "{}", a.text());
    assert_eq!(a.json()["result"]["objects"][0]["status"], "ok", "{}", a.text());
    // Refused uploads leave no job folder behind.
    assert_eq!(std::fs::read_dir(t.join("data/jobs")).unwrap().count(), 1);
    assert!(!server.logs().contains("panicked"), "{}", server.logs());
    let _ = std::fs::remove_dir_all(&t);
}

fn percentile(v: &mut [f64], p: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * p).round() as usize]
}

/// 32 clients send 4 requests each at once against `--workers 2 --queue 8`: every answer
/// is 200 or 429 (with Retry-After), every 200 is a complete, correct job, and the
/// server's memory stays bounded.
#[test]
fn load_gets_200_or_429_and_every_200_is_right() {
    const CLIENTS: usize = 32;
    const PER_CLIENT: usize = 4;
    let t = tmp("serve-load");
    let server = Server::tiny(&t.join("data"), &["--workers", "2", "--queue", "8"]);
    let s = std::sync::Arc::new(sample());
    let (ct, body) = multipart(&tiny_parts(&s, FAST));
    let (ct, body) = (std::sync::Arc::new(ct), std::sync::Arc::new(body));
    let url = server.url("/v1/reconstruct");
    let t0 = Instant::now();
    let handles: Vec<_> = (0..CLIENTS)
        .map(|_| {
            let (ct, body, url) = (ct.clone(), body.clone(), url.clone());
            std::thread::spawn(move || {
                (0..PER_CLIENT)
                    .map(|_| {
                        let t = Instant::now();
                        let a = request("POST", &url, Some((&ct, &body)), None);
                        (a.status, t.elapsed().as_secs_f64(), a.header("retry-after").map(str::to_string), a.body)
                    })
                    .collect::<Vec<_>>()
            })
        })
        .collect();
    let results: Vec<_> = handles.into_iter().flat_map(|h| h.join().unwrap()).collect();
    let wall = t0.elapsed().as_secs_f64();
    let mut ok_s = Vec::new();
    for (status, secs, retry, body) in &results {
        match status {
            200 => {
                let j: serde_json::Value = serde_json::from_slice(body).unwrap();
                let o = &j["result"]["objects"][0];
                assert_eq!((j["status"].as_str(), o["status"].as_str(), o["id"].as_u64()), (Some("done"), Some("ok"), Some(8)), "{j}");
                let f = get(&server.url(o["files"]["gaussians_ply"].as_str().unwrap()));
                assert!(f.status == 200 && f.body.starts_with(b"ply"));
                ok_s.push(*secs);
            }
            429 => assert!(retry.as_deref().and_then(|r| r.parse::<u64>().ok()).is_some_and(|r| r >= 1), "429 without Retry-After"),
            other => panic!("status {other}: {}", String::from_utf8_lossy(body)),
        }
    }
    let n429 = results.len() - ok_s.len();
    assert_eq!(results.len(), CLIENTS * PER_CLIENT);
    assert!(ok_s.len() >= 10, "{} of {} got 200", ok_s.len(), results.len());
    let metrics = get(&server.url("/metrics")).text();
    let peak: f64 = metrics.lines().find_map(|l| l.strip_prefix("recon_peak_resident_memory_bytes ")).unwrap().parse().unwrap();
    let (p50, p99) = (percentile(&mut ok_s.clone(), 0.5), percentile(&mut ok_s, 0.99));
    eprintln!(
        "load: {} requests in {wall:.1} s: {} × 200 (p50 {p50:.2} s, p99 {p99:.2} s), {n429} × 429; server peak RSS {:.0} MiB",
        results.len(),
        ok_s.len(),
        peak / 1048576.0
    );
    assert!(peak < 4e9, "peak RSS {peak}");
    assert!(metrics.contains("recon_stage_seconds_bucket{stage=\"total\""), "{metrics}");
    let _ = std::fs::remove_dir_all(&t);
}

fn job_id(a: &Answer) -> String {
    a.json()["id"].as_str().unwrap().to_string()
}

/// kill -9 while a job runs and another waits, then a restart on the same folder: the
/// finished job is served byte-identical, the running one is reported failed
/// (interrupted), the queued one runs. Then SIGTERM with a job running: it finishes,
/// the server exits 0, and a job still queued runs after the next start.
#[test]
fn kill_9_and_sigterm_keep_every_job() {
    let t = tmp("serve-kill");
    let data = t.join("data");
    let s = sample();
    let slow = br#"{"max_faces": 20000, "samples": 6, "steps": 3}"#;
    let mut server = Server::tiny(&data, &[]);
    let done = post_parts(&server, "", &tiny_parts(&s, FAST));
    assert_eq!(done.status, 200, "{}", done.text());
    let done_id = job_id(&done);
    let archive = get(&server.url(&format!("/v1/jobs/{done_id}/archive"))).body;
    let running = job_id(&post_parts(&server, "?wait=false", &tiny_parts(&s, slow)));
    let queued = post_parts(&server, "?wait=false", &tiny_parts(&s, FAST));
    assert_eq!(queued.status, 202);
    let queued = job_id(&queued);
    wait_status(&server, &running, &["running"], 120);
    server.kill9();
    assert!(!data.join("jobs").join(&running).join("out").exists());

    let server = Server::tiny(&data, &[]);
    let again = get(&server.url(&format!("/v1/jobs/{done_id}/archive")));
    assert!(again.status == 200 && again.body == archive, "the finished job changed across the restart");
    let j = get(&server.url(&format!("/v1/jobs/{running}"))).json();
    assert_eq!((j["status"].as_str(), j["error"]["reason"].as_str()), (Some("failed"), Some("interrupted")), "{j}");
    let f = get(&server.url(&format!("/v1/jobs/{running}/files/recon-output.json")));
    assert_eq!(f.status, 409, "an interrupted job serves no files");
    wait_status(&server, &queued, &["done"], 300);
    drop(server);

    // SIGTERM with one job running and one queued (one worker).
    let mut server = Server::tiny(&data, &["--shutdown-grace-s", "300"]);
    let running = job_id(&post_parts(&server, "?wait=false", &tiny_parts(&s, br#"{"max_faces": 20000, "samples": 2}"#)));
    let queued = job_id(&post_parts(&server, "?wait=false", &tiny_parts(&s, FAST)));
    wait_status(&server, &running, &["running"], 120);
    unsafe { libc::kill(server.child.id() as i32, libc::SIGTERM) };
    let t0 = Instant::now();
    let status = loop {
        if let Some(st) = server.child.try_wait().unwrap() {
            break st;
        }
        assert!(t0.elapsed() < Duration::from_secs(120), "no exit after SIGTERM\n{}", server.logs());
        std::thread::sleep(Duration::from_millis(50));
    };
    assert!(status.success(), "exit {status:?}\n{}", server.logs());
    let state = |id: &str| common::read_json(&data.join("jobs").join(id).join("state.json"));
    assert_eq!(state(&running)["status"], "done", "the running job finished within the grace period");
    assert_eq!(state(&queued)["status"], "queued");
    let server = Server::tiny(&data, &[]);
    wait_status(&server, &queued, &["done"], 300);
    let _ = std::fs::remove_dir_all(&t);
}

/// A `wait=true` client that goes away cancels its job; DELETE cancels a running job at
/// its next stage boundary and deletes a finished one.
#[test]
fn disconnect_and_delete_cancel() {
    let t = tmp("serve-cancel");
    let data = t.join("data");
    let server = Server::tiny(&data, &[]);
    let s = sample();
    let slow = br#"{"max_faces": 20000, "samples": 8, "steps": 3}"#;
    let (ct, body) = multipart(&tiny_parts(&s, slow));
    let mut c = std::net::TcpStream::connect(server.addr).unwrap();
    write!(c, "POST /v1/reconstruct HTTP/1.1\r\nHost: x\r\nContent-Type: {ct}\r\nContent-Length: {}\r\n\r\n", body.len()).unwrap();
    c.write_all(&body).unwrap();
    let t0 = Instant::now();
    let id = loop {
        let ids: Vec<String> =
            std::fs::read_dir(data.join("jobs")).unwrap().flatten().map(|e| e.file_name().to_string_lossy().to_string()).collect();
        if let Some(id) = ids.iter().find(|id| data.join("jobs").join(id).join("state.json").exists()) {
            break id.clone();
        }
        assert!(t0.elapsed() < Duration::from_secs(60));
        std::thread::sleep(Duration::from_millis(20));
    };
    wait_status(&server, &id, &["running"], 120);
    drop(c);
    let j = wait_status(&server, &id, &["cancelled", "done", "failed"], 120);
    assert_eq!((j["status"].as_str(), j["error"]["reason"].as_str()), (Some("cancelled"), Some("client disconnected")), "{j}");

    let id = job_id(&post_parts(&server, "?wait=false", &tiny_parts(&s, slow)));
    wait_status(&server, &id, &["running"], 120);
    let d = request("DELETE", &server.url(&format!("/v1/jobs/{id}")), None, None);
    assert_eq!(d.status, 202, "{}", d.text());
    let t0 = Instant::now();
    let j = wait_status(&server, &id, &["cancelled", "done", "failed"], 120);
    eprintln!("DELETE of a running job: cancelled after {:.2} s", t0.elapsed().as_secs_f64());
    assert_eq!(j["status"], "cancelled", "{j}");
    let d = request("DELETE", &server.url(&format!("/v1/jobs/{id}")), None, None);
    assert_eq!((d.status, d.json()["deleted"].as_bool()), (200, Some(true)));
    assert_eq!(get(&server.url(&format!("/v1/jobs/{id}"))).status, 404);
    assert!(!data.join("jobs").join(&id).exists());
    let _ = std::fs::remove_dir_all(&t);
}

/// With a token every route but /health needs it; file routes stay inside the job's
/// folder; the OpenAPI document lists every route and each answers; a finished job
/// becomes a scene; a non-loopback bind without a token is refused at start.
#[test]
fn auth_paths_openapi_and_scene() {
    let t = tmp("serve-auth");
    let data = t.join("data");
    std::fs::write(t.join("token"), "s3cret\n").unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_recon"))
        .args(["serve", "--bind", "0.0.0.0:0", "--data-dir", data.to_str().unwrap(), "--weights", "random"])
        .current_dir(repo())
        .env_remove("RECON_API_TOKEN")
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("--bind: 0.0.0.0:0 is reachable from other machines"), "{err}");

    let server = Server::tiny(&data, &["--token-file", t.join("token").to_str().unwrap()]);
    let tok = Some("s3cret");
    assert_eq!(get(&server.url("/health")).status, 200);
    assert_eq!(get(&server.url("/ready")).status, 401);
    let a = request("GET", &server.url("/ready"), None, Some("wrong"));
    assert_eq!((a.status, a.header("www-authenticate")), (401, Some("Bearer")));
    assert_eq!(request("GET", &server.url("/ready"), None, tok).status, 200);
    let s = sample();
    let (ct, body) = multipart(&tiny_parts(&s, FAST));
    // A client that sends its whole body before reading still reads the 401 (lingering close).
    assert_eq!(request("POST", &server.url("/v1/reconstruct"), Some((&ct, &body)), None).status, 401);
    let a = request("POST", &server.url("/v1/reconstruct"), Some((&ct, &body)), tok);
    assert_eq!(a.status, 200, "{}", a.text());
    let id = job_id(&a);

    // Path traversal: raw requests, since clients normalise `..`.
    let out = data.join("jobs").join(&id).join("out");
    std::os::unix::fs::symlink(data.join("jobs").join(&id).join("state.json"), out.join("link.json")).unwrap();
    for path in [
        "../state.json",
        "%2e%2e/state.json",
        "..%2fstate.json",
        "/etc/passwd",
        "%2fetc%2fpasswd",
        "link.json",
        "id_8/../../state.json",
        "id_8",
    ] {
        let req =
            format!("GET /v1/jobs/{id}/files/{path} HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer s3cret\r\nConnection: close\r\n\r\n");
        let (st, text) = raw(server.addr, req.as_bytes());
        assert_eq!(st, 404, "{path}: {text}");
    }
    let req = format!(
        "GET /v1/jobs/{id}/files/recon-output.json HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer s3cret\r\nConnection: close\r\n\r\n"
    );
    assert_eq!(raw(server.addr, req.as_bytes()).0, 200);
    assert_eq!(request("GET", &server.url("/v1/jobs/0123/files/x"), None, tok).status, 404);

    // The scene of the finished job.
    let a = request("POST", &server.url(&format!("/v1/jobs/{id}/scene")), Some(("application/json", br#"{"settle_time": 0.5}"#)), tok);
    assert_eq!(a.status, 200, "{}", a.text());
    let files = a.json()["files"].as_array().unwrap().iter().map(|f| f.as_str().unwrap().to_string()).collect::<Vec<_>>();
    let urdf = files.iter().find(|f| f.ends_with(".urdf")).expect("a URDF");
    assert_eq!(request("GET", &server.url(urdf), None, tok).status, 200);
    let a = request("POST", &server.url(&format!("/v1/jobs/{id}/scene")), Some(("application/json", br#"{"colision": "convex"}"#)), tok);
    assert_eq!((a.status, error_of(&a).2.as_str()), (400, "colision"));

    // Every documented route exists (a 404 from the router says "no such route").
    let doc = request("GET", &server.url("/openapi.json"), None, tok).json();
    let mut n = 0;
    for (path, ops) in doc["paths"].as_object().unwrap() {
        for method in ops.as_object().unwrap().keys() {
            let p = path.replace("{id}", &id).replace("{path}", "recon-output.json");
            let p = if p.contains("/scene/files/") { p.replace("recon-output.json", "scene.json") } else { p };
            let m = method.to_uppercase();
            if m == "DELETE" {
                continue; // below, last
            }
            let body = (m == "POST").then_some(("application/json", &b"{}"[..]));
            let a = request(&m, &server.url(&p), body, tok);
            assert!(a.status != 405 && !a.text().contains("no such route"), "{m} {p}: {} {}", a.status, a.text());
            n += 1;
        }
    }
    let route_count = recon_serve::ROUTES.len();
    assert_eq!(n + 1, route_count, "the document lists {} operations, the router has {route_count}", n + 1);
    let a = request("GET", &server.url("/v1/nothing"), None, tok);
    assert!(a.status == 404 && a.text().contains("no such route"));
    assert_eq!(request("DELETE", &server.url(&format!("/v1/jobs/{id}")), None, tok).status, 200);
    let metrics = request("GET", &server.url("/metrics"), None, tok).text();
    assert!(metrics.contains("recon_queue_depth 0") && metrics.contains("recon_jobs_total{status=\"done\"} 1"), "{metrics}");
    let _ = std::fs::remove_dir_all(&t);
}

/// A write that fails mid-job (the data folder on a 1.2 MB tmpfs: the inputs fit, the
/// outputs do not): the job fails with reason `write` and the disk's message, nothing of
/// it is served, and the server goes on. Skipped where tmpfs cannot be mounted (not root).
#[test]
fn a_full_disk_fails_the_job_cleanly() {
    let t = tmp("serve-full");
    let data = t.join("data");
    std::fs::create_dir_all(&data).unwrap();
    let mounted = Command::new("mount").args(["-t", "tmpfs", "-o", "size=1200k", "tmpfs"]).arg(&data).status().is_ok_and(|s| s.success());
    if !mounted {
        eprintln!("skipped: cannot mount a tmpfs here");
        return;
    }
    struct Unmount(PathBuf);
    impl Drop for Unmount {
        fn drop(&mut self) {
            let _ = Command::new("umount").arg("-l").arg(&self.0).status();
        }
    }
    let _unmount = Unmount(data.clone());
    let server = Server::tiny(&data, &[]);
    let s = sample();
    let a = post_parts(&server, "", &tiny_parts(&s, FAST));
    let j = a.json();
    assert_eq!((a.status, j["status"].as_str(), j["error"]["reason"].as_str()), (503, Some("failed"), Some("write")), "{j}");
    assert!(j["error"]["message"].as_str().unwrap().contains("No space left"), "{j}");
    let id = j["id"].as_str().unwrap();
    assert_eq!(get(&server.url(&format!("/v1/jobs/{id}/files/recon-output.json"))).status, 409);
    assert_eq!(get(&server.url(&format!("/v1/jobs/{id}/archive"))).status, 409);
    let job = data.join("jobs").join(id);
    assert!(!job.join("out").exists() && !job.join("out.partial").exists());
    assert_eq!(common::read_json(&job.join("state.json"))["status"], "failed");
    assert_eq!(get(&server.url("/health")).status, 200);
    drop(server);
    drop(_unmount);
    let _ = std::fs::remove_dir_all(&t);
}

/// `--job-timeout-s`: a job running past it stops at its next stage boundary, `failed`
/// with reason `timeout`, and a `wait=true` client gets 504. `--keep-hours`: finished jobs
/// older than that are deleted (here 0.0003 h ≈ 1 s).
#[test]
fn timeout_and_retention() {
    let t = tmp("serve-timeout");
    let data = t.join("data");
    let server = Server::tiny(&data, &["--job-timeout-s", "1", "--keep-hours", "0.0003"]);
    let s = sample();
    let a = post_parts(&server, "", &tiny_parts(&s, br#"{"max_faces": 20000, "samples": 8, "steps": 3}"#));
    let j = a.json();
    assert_eq!((a.status, j["status"].as_str(), j["error"]["reason"].as_str()), (504, Some("failed"), Some("timeout")), "{j}");
    let id = j["id"].as_str().unwrap();
    let t0 = Instant::now();
    while get(&server.url(&format!("/v1/jobs/{id}"))).status != 404 {
        assert!(t0.elapsed() < Duration::from_secs(30), "job {id} not deleted by --keep-hours");
        std::thread::sleep(Duration::from_millis(100));
    }
    assert!(!data.join("jobs").join(id).exists());
    // The event is logged after the deletion, and the log is read from the server's
    // output stream: under load it can arrive a moment after the 404.
    while !server.logs().contains("\"event\":\"retention\"") {
        assert!(t0.elapsed() < Duration::from_secs(60), "no retention event logged: {}", server.logs());
        std::thread::sleep(Duration::from_millis(100));
    }
    let _ = std::fs::remove_dir_all(&t);
}

/// The other input forms: binary mask parts (objects named by their file names), `.npy`
/// float32 depth in metres, intrinsics as a 3×3 `K`; and a second view (the same frame,
/// `T_c1_c2` the identity), whose objects pair by instance id.
#[test]
fn binary_masks_npy_depth_k_and_a_second_view() {
    let t = tmp("serve-forms");
    let server = Server::tiny(&t.join("data"), &[]);
    let s = sample();
    let label = image::load_from_memory(&s.label).unwrap().to_luma8();
    let mask = |id: u8| {
        let m = image::GrayImage::from_fn(label.width(), label.height(), |x, y| {
            image::Luma([if label.get_pixel(x, y).0[0] == id { 255 } else { 0 }])
        });
        let mut out = Vec::new();
        m.write_to(&mut std::io::Cursor::new(&mut out), image::ImageFormat::Png).unwrap();
        out
    };
    let depth = image::load_from_memory(&s.depth).unwrap().to_luma16();
    let intr: serde_json::Value = serde_json::from_slice(&s.intrinsics).unwrap();
    let scale = intr["depth_scale_m"].as_f64().unwrap();
    let mut header = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': ({}, {}), }}", depth.height(), depth.width());
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut npy = b"\x93NUMPY\x01\x00".to_vec();
    npy.extend((header.len() as u16).to_le_bytes());
    npy.extend(header.as_bytes());
    for v in depth.pixels() {
        npy.extend(((v.0[0] as f64 * scale) as f32).to_le_bytes());
    }
    let k = serde_json::json!({"K": [[intr["fx"], 0, intr["cx"]], [0, intr["fy"], intr["cy"]], [0, 0, 1]]}).to_string();
    let (m8, m14) = (mask(8), mask(14));
    let a = post_parts(
        &server,
        "",
        &[
            ("rgb", Some("shot.png"), &s.rgb),
            ("depth", Some("shot.npy"), &npy),
            ("masks", Some("gelatin.png"), &m8),
            ("masks", Some("mug.png"), &m14),
            ("intrinsics", None, k.as_bytes()),
            ("options", None, FAST),
        ],
    );
    assert_eq!(a.status, 200, "{}", a.text());
    let j = a.json();
    let labels: Vec<&str> = j["result"]["objects"].as_array().unwrap().iter().map(|o| o["label"].as_str().unwrap()).collect();
    assert_eq!(labels, ["gelatin.png", "mug.png"], "{j}");
    assert!(j["result"]["objects"].as_array().unwrap().iter().all(|o| o["status"] == "ok"), "{j}");

    let mut two = tiny_parts(&s, FAST);
    two.extend([
        ("rgb2", Some("b.png"), &s.rgb[..]),
        ("depth2", Some("b-depth.png"), &s.depth[..]),
        ("masks2", Some("b-label.png"), &s.label[..]),
        ("intrinsics2", None, &s.intrinsics[..]),
        ("T_c1_c2", None, &b"[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]"[..]),
    ]);
    let a = post_parts(&server, "", &two);
    assert_eq!(a.status, 200, "{}", a.text());
    let o = &a.json()["result"]["objects"][0];
    assert_eq!(o["status"], "ok", "{o}");
    let pose = get(&server.url(o["files"]["pose"].as_str().unwrap())).json();
    assert_eq!(pose["views"].as_array().unwrap().len(), 2, "{pose}");
    assert_eq!(pose["views"][1]["frame"], "b.png");
    // The colour calibration: its record in the answer and its file.
    let a = post_parts(&server, "", &tiny_parts(&s, br#"{"max_faces": 20000, "posthoc_color": "gamma_affine"}"#));
    assert_eq!(a.status, 200, "{}", a.text());
    let o = &a.json()["result"]["objects"][0];
    assert_eq!(o["posthoc_color"]["variant"], "gamma_affine", "{o}");
    let file = get(&server.url(o["files"]["posthoc_color"].as_str().unwrap())).json();
    assert_eq!(file, o["posthoc_color"]);
    let _ = std::fs::remove_dir_all(&t);
}

/// Three views over HTTP (the anchor and views 2 and 3: the sample frame again, moved by
/// small rigid shifts) give the files `recon infer --view v2.json --view v3.json` writes
/// with the same model and options, byte for byte (JSON: but for the timing fields); the
/// two-view tiny model fuses (anchor, view i) pairs, the answer lists each object's views
/// as `recon infer --json` does, and an id in no view is skipped in each, as the CLI lists it.
#[test]
fn three_views_over_http_match_recon_infer() {
    let t = tmp("serve-views");
    let s = sample();
    for (name, bytes) in
        [("000001-color.png", &s.rgb), ("000001-depth.png", &s.depth), ("000001-label.png", &s.label), ("K.json", &s.intrinsics)]
    {
        std::fs::write(t.join(name), bytes).unwrap();
    }
    let config = repo().join("models/recgen-tiny.json");
    let model = ["--weights", "random", "--config", config.to_str().unwrap(), "--steps", "1"];
    let server = Server::start(&t.join("data"), &t, &model, &[]);
    let (t2, t3) = ("[[1,0,0,0.03],[0,1,0,0],[0,0,1,0],[0,0,0,1]]", "0 1 0 0  -1 0 0 -0.04  0 0 1 0.01  0 0 0 1");
    let options = br#"{"max_faces": 20000, "slat_fusion": "multidiffusion"}"#;
    let mut parts: Vec<(&str, Option<&str>, &[u8])> = vec![
        ("rgb", Some("000001-color.png"), &s.rgb),
        ("depth", Some("000001-depth.png"), &s.depth),
        ("masks", Some("000001-label.png"), &s.label),
        ("intrinsics", Some("K.json"), &s.intrinsics),
        ("objects", None, b"8,99"),
        ("options", None, options),
    ];
    for (names, pose) in
        [(["rgb2", "depth2", "masks2", "intrinsics2", "T_c1_c2"], t2), (["rgb3", "depth3", "masks3", "intrinsics3", "T_c1_c3"], t3)]
    {
        parts.extend([
            (names[0], Some("000001-color.png"), &s.rgb[..]),
            (names[1], Some("000001-depth.png"), &s.depth[..]),
            (names[2], Some("000001-label.png"), &s.label[..]),
            (names[3], Some("K.json"), &s.intrinsics[..]),
            (names[4], None, pose.as_bytes()),
        ]);
    }
    let a = post_parts(&server, "", &parts);
    assert_eq!(a.status, 200, "{}\n{}", a.text(), server.logs());
    let job = a.json();
    let id = job["id"].as_str().unwrap().to_string();
    let o = &job["result"]["objects"][0];
    assert_eq!(o["status"], "ok", "{job:#}");
    // Id 99 is in no view: each view's mask skip is listed, as recon infer lists them.
    let rest: Vec<(&str, &str, u64)> = job["result"]["objects"].as_array().unwrap()[1..]
        .iter()
        .map(|x| (x["status"].as_str().unwrap(), x["label"].as_str().unwrap(), x["id"].as_u64().unwrap()))
        .collect();
    assert_eq!(rest, [("skipped", "id 99", 99), ("skipped", "view 2 id 99", 99), ("skipped", "view 3 id 99", 99)], "{job:#}");
    let views: Vec<u64> = o["views"].as_array().unwrap().iter().map(|v| v["view"].as_u64().unwrap()).collect();
    assert_eq!(views, [1, 2, 3], "{o:#}");
    assert!((1..=3).contains(&o["selection"]["view"].as_u64().unwrap()), "{o:#}");
    let pose = get(&server.url(o["files"]["pose"].as_str().unwrap())).json();
    // The answer's views are pose.json's (there f32 numbers are written widened to f64).
    let views_of = |v: &serde_json::Value| -> Vec<(u64, String, String)> {
        v.as_array().unwrap().iter().map(|x| (x["view"].as_u64().unwrap(), x["mask"].to_string(), x["frame"].to_string())).collect()
    };
    assert_eq!(views_of(&pose["views"]), views_of(&o["views"]));
    assert_eq!(pose["run"]["fusion"], serde_json::json!({"pairs": 2, "ss": "multidiffusion", "slat": "multidiffusion"}), "{pose:#}");
    let served = unzip(&get(&server.url(&format!("/v1/jobs/{id}/archive"))).body);
    drop(server);

    // recon infer with the same views as --view files, written where the server wrote.
    for (name, pose) in [("v2.json", t2), ("v3.json", t3)] {
        let nums: Vec<f64> =
            pose.replace(['[', ']'], " ").split([',', ' ']).filter(|x| !x.is_empty()).map(|x| x.parse().unwrap()).collect();
        let v = serde_json::json!({"rgb": "000001-color.png", "depth": "000001-depth.png", "masks": "000001-label.png",
            "intrinsics": "K.json", "T_c1_ci": nums});
        std::fs::write(t.join(name), v.to_string()).unwrap();
    }
    let out = t.join("data/jobs").join(&id).join("out");
    let o = Command::new(env!("CARGO_BIN_EXE_recon"))
        .args(["infer", "--rgbd", "000001-color.png", "--masks", "000001-label.png", "--depth", "000001-depth.png"])
        .args(["--intrinsics", "K.json", "--objects", "8,99", "--view", "v2.json", "--view", "v3.json"])
        .args(model)
        .args(["--max-faces", "20000", "--slat-fusion", "multidiffusion"])
        .arg("--out")
        .arg(&out)
        .current_dir(&t)
        .output()
        .unwrap();
    // Exit 3: some objects written, others not (id 99).
    assert_eq!(o.status.code(), Some(3), "{}", String::from_utf8_lossy(&o.stderr));
    assert_same_files(&out, &served);
    let _ = std::fs::remove_dir_all(&t);
}

/// Bad views besides the anchor: each a 400 naming the part and the field, refused
/// before a job is queued.
#[test]
fn bad_views_are_400s_naming_part_and_field() {
    let t = tmp("serve-bad-views");
    let server = Server::tiny(&t.join("data"), &[]);
    let s = sample();
    let leak = |b: &[u8]| -> &'static [u8] { Box::leak(b.to_vec().into_boxed_slice()) };
    let (rgb, depth, label, intr) = (leak(&s.rgb), leak(&s.depth), leak(&s.label), leak(&s.intrinsics));
    let identity: &'static [u8] = b"[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]";
    type Parts = Vec<(&'static str, Option<&'static str>, &'static [u8])>;
    let view = |k: usize, pose: &'static [u8]| -> Parts {
        let n = |p: &str| -> &'static str { Box::leak(format!("{p}{k}").into_boxed_str()) };
        vec![
            (n("rgb"), Some("b.png"), rgb),
            (n("depth"), Some("b-depth.png"), depth),
            (n("masks"), Some("b-label.png"), label),
            (n("intrinsics"), None, intr),
            (n("T_c1_c"), None, pose),
        ]
    };
    let request = |views: Vec<Parts>, drop: &[&str]| {
        let mut parts = tiny_parts(&s, FAST);
        parts.extend(views.into_iter().flatten().filter(|p| !drop.contains(&p.0)));
        parts
    };
    let check = |what: &str, parts: Vec<(&str, Option<&str>, &[u8])>, status: u16, part: &str, field: &str, msg: &str| {
        let a = post_parts(&server, "", &parts);
        let (st, p, f, m) = error_of(&a);
        assert_eq!((st, p.as_str(), f.as_str()), (status, part, field), "{what}: {m}");
        assert!(m.contains(msg), "{what}: `{m}` lacks `{msg}`");
        eprintln!("{what}: {st} part={p} field={f}: {m}");
    };
    check("view 4 without view 3", request(vec![view(2, identity), view(4, identity)], &[]), 400, "rgb3", "rgb3", "view 4 is given");
    check(
        "view 3 without masks3",
        request(vec![view(2, identity), view(3, identity)], &["masks3"]),
        400,
        "masks3",
        "masks3",
        "view 3 needs rgb3, depth3, masks3, intrinsics3 and T_c1_c3 (given: rgb3, depth3, intrinsics3, T_c1_c3)",
    );
    check(
        "view 18",
        request(vec![view(2, identity), view(18, identity)], &[]),
        400,
        "rgb18",
        "name",
        "at most 16 views besides the anchor",
    );
    let scaled: &'static [u8] = b"2,0,0,0, 0,2,0,0, 0,0,2,0, 0,0,0,1";
    check(
        "non-rigid T_c1_c3",
        request(vec![view(2, identity), view(3, scaled)], &[]),
        400,
        "T_c1_c3",
        "T_c1_c3",
        "T_c1_c3: T_c1_c3: the 3×3 block is not a rotation",
    );
    check(
        "T_c1_c3 of 3 numbers",
        request(vec![view(2, identity), view(3, br#"{"T_c1_c3": [1, 2, 3]}"#)], &[]),
        400,
        "T_c1_c3",
        "T_c1_c3",
        "T_c1_c3 needs 16 finite numbers (4×4, row-major), got 3",
    );
    check("T_c1_c3 as words", request(vec![view(2, identity), view(3, b"one two")], &[]), 400, "T_c1_c3", "T_c1_c3", "is not 16 numbers");
    let big: &'static [u8] = leak(&vec![b' '; (1 << 20) + 1]);
    check(
        "huge intrinsics3",
        request(vec![view(2, identity), view(3, identity)], &[])
            .into_iter()
            .map(|p| if p.0 == "intrinsics3" { (p.0, p.1, big) } else { p })
            .collect(),
        413,
        "intrinsics3",
        "bytes",
        "intrinsics3: more than 1048576 bytes",
    );
    check(
        "unknown part",
        request(vec![view(2, identity)], &[]).into_iter().chain([("rgb03", None, rgb)]).collect(),
        400,
        "rgb03",
        "name",
        "rgbN, depthN, masksN, intrinsicsN, T_c1_cN",
    );
    // Nothing was queued; the server still serves.
    assert_eq!(std::fs::read_dir(t.join("data/jobs")).map_or(0, |d| d.count()), 0);
    assert_eq!(get(&server.url("/health")).status, 200);
    assert!(!server.logs().contains("panicked"), "{}", server.logs());
    let _ = std::fs::remove_dir_all(&t);
}

/// Runs `recon args…` from the repository and waits for it with `wait4`: its exit status,
/// its stdout and stderr, its seconds and its peak resident memory (MiB, the kernel's
/// `ru_maxrss` of that process).
// The child is reaped by `wait4`, which clippy does not see.
#[allow(clippy::zombie_processes)]
fn recon_measured(args: &[&str]) -> (i32, String, String, f64, f64) {
    let out_file = tmp("measured-out").with_extension(format!("{}.txt", std::process::id()));
    let err_file = out_file.with_extension("err");
    let t0 = Instant::now();
    let child = Command::new(env!("CARGO_BIN_EXE_recon"))
        .args(args)
        .current_dir(repo())
        .stdout(std::fs::File::create(&out_file).unwrap())
        .stderr(std::fs::File::create(&err_file).unwrap())
        .spawn()
        .unwrap();
    let (mut status, mut usage) = (0i32, unsafe { std::mem::zeroed::<libc::rusage>() });
    // SAFETY: waits for our own child; `status` and `usage` are valid for writes.
    let pid = unsafe { libc::wait4(child.id() as libc::pid_t, &mut status, 0, &mut usage) };
    assert_eq!(pid, child.id() as libc::pid_t, "wait4");
    let secs = t0.elapsed().as_secs_f64();
    let code = if libc::WIFEXITED(status) { libc::WEXITSTATUS(status) } else { -1 };
    let (out, err) = (std::fs::read_to_string(&out_file).unwrap(), std::fs::read_to_string(&err_file).unwrap());
    let _ = (std::fs::remove_file(&out_file), std::fs::remove_file(&err_file));
    (code, out, err, secs, usage.ru_maxrss as f64 / 1024.0)
}

/// An instance-id PNG of the README sample's size (640×480, 16-bit) with 20 000 one-pixel
/// instances: through `recon infer` and through the server it completes, skips every
/// instance (nothing is left after erosion), and stays within a few hundred MB: masks are
/// held as row runs and checked on them, no full-frame buffer per instance. Before, this
/// took 195 s and 6.1 GB to skip them all. `max_objects` refuses a frame with more
/// objects that pass the checks, naming the count and the limit, through both.
#[test]
fn twenty_thousand_one_pixel_instances_stay_small() {
    let t = tmp("serve-many-masks");
    let d = repo().join("data/sample");
    let (w, h) = (640u32, 480u32);
    let n = 20_000u32;
    let map = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_fn(w, h, |x, y| {
        // Every other pixel of every other row: no two instances touch.
        let i = (y / 2) * (w / 2) + x / 2;
        image::Luma([if x % 2 == 0 && y % 2 == 0 && i < n { (i + 1) as u16 } else { 0 }])
    });
    let masks = t.join("many-label.png");
    map.save(&masks).unwrap();
    let out = t.join("many_recon");
    let rgb = d.join("000001-color.png");
    let (code, stdout, stderr, secs, peak) = recon_measured(&[
        "infer",
        "--rgbd",
        rgb.to_str().unwrap(),
        "--masks",
        masks.to_str().unwrap(),
        "--weights",
        "random",
        "--config",
        "models/recgen-tiny.json",
        "--out",
        out.to_str().unwrap(),
    ]);
    eprintln!("recon infer, {n} one-pixel instances: {secs:.1} s, peak RSS {peak:.0} MiB");
    // Exit 2: no object could be reconstructed; every instance is listed as skipped.
    assert_eq!(code, 2, "{stderr}");
    let skipped = stdout.lines().filter(|l| l.contains(": skipped: mask of 1 px is empty after erosion")).count();
    assert_eq!(skipped, n as usize, "{}", &stdout[..stdout.len().min(2000)]);
    assert!(peak < 600.0, "recon infer peak RSS {peak:.0} MiB");

    let server = Server::tiny(&t.join("data"), &[]);
    let s = sample();
    let many = std::fs::read(&masks).unwrap();
    let parts = [
        ("rgb", Some("000001-color.png"), s.rgb.as_slice()),
        ("depth", Some("000001-depth.png"), s.depth.as_slice()),
        ("masks", Some("many-label.png"), many.as_slice()),
        ("intrinsics", None, s.intrinsics.as_slice()),
    ];
    let t0 = Instant::now();
    let a = post_parts(&server, "", &parts);
    let http_s = t0.elapsed().as_secs_f64();
    assert_eq!(a.status, 200, "{}", a.text());
    let j = a.json();
    let objects = j["result"]["objects"].as_array().unwrap();
    assert_eq!(objects.len(), n as usize);
    assert!(objects.iter().all(|o| o["status"] == "skipped"), "{}", objects[0]);
    let metrics = get(&server.url("/metrics")).text();
    let peak: f64 = metrics.lines().find_map(|l| l.strip_prefix("recon_peak_resident_memory_bytes ")).unwrap().parse().unwrap();
    let peak = peak / 1048576.0;
    eprintln!("recon serve, {n} one-pixel instances: {http_s:.1} s round trip, server peak RSS {peak:.0} MiB");
    assert!(peak < 600.0, "recon serve peak RSS {peak:.0} MiB");

    // max_objects: the sample has several objects that pass; 1 is refused, naming 1 and the count.
    let (code, _, stderr, _, _) = recon_measured(&[
        "infer",
        "--rgbd",
        rgb.to_str().unwrap(),
        "--masks",
        d.join("000001-label.png").to_str().unwrap(),
        "--weights",
        "random",
        "--config",
        "models/recgen-tiny.json",
        "--max-objects",
        "1",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(code, 1, "{stderr}");
    assert!(stderr.contains("--masks: max_objects claims") && stderr.contains("more than the limit of 1 "), "{stderr}");
    let opts = br#"{"max_objects": 1}"#;
    let parts = [
        ("rgb", Some("000001-color.png"), s.rgb.as_slice()),
        ("depth", Some("000001-depth.png"), s.depth.as_slice()),
        ("masks", Some("000001-label.png"), s.label.as_slice()),
        ("intrinsics", None, s.intrinsics.as_slice()),
        ("options", None, opts.as_slice()),
    ];
    let (status, part, field, message) = error_of(&post_parts(&server, "", &parts));
    assert_eq!((status, part.as_str(), field.as_str()), (413, "masks", "max_objects"), "{message}");
    assert!(message.contains("more than the limit of 1 "), "{message}");
    // A request may lower the server's --max-objects, not raise it.
    let (status, part, field, message) = error_of(&post_parts(&server, "", &tiny_parts(&s, br#"{"max_objects": 100000}"#)));
    assert_eq!((status, part.as_str(), field.as_str()), (400, "options", "max_objects"), "{message}");
    assert!(message.contains("256"), "{message}");
    let _ = std::fs::remove_dir_all(&t);
}
