//! The HTTP side: the router built from [`crate::ROUTES`], its handlers, the token check,
//! the request log, and starting and stopping the server.

use crate::config::ServeConfig;
use crate::error::{ApiError, ServeError};
use crate::inputs::{self, is_repeatable, is_small_part, Manifest, StoredPart, MAX_SMALL_PART_BYTES};
use crate::jobs::{valid_id, CancelReason, Job, Jobs, Status};
use crate::log::{log, peak_mib};
use crate::openapi::{axum_path, openapi, Route, ROUTES};
use crate::paths;
use axum::body::Body;
use axum::extract::{DefaultBodyLimit, FromRequest, Multipart, Path as UrlPath, Query, Request, State};
use axum::http::{header, HeaderValue, StatusCode};
use axum::middleware::{from_fn_with_state, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{delete, get, post, MethodRouter};
use axum::{Json, Router};
use recon_core::engine::Engine;
use std::collections::{BTreeMap, HashSet};
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};
use tokio::io::AsyncWriteExt;
use tokio::sync::watch;

/// What every handler shares.
#[derive(Clone)]
struct App {
    jobs: Arc<Jobs>,
    shutdown: watch::Receiver<bool>,
    /// Jobs whose scene is being built (one at a time per job).
    scenes: Arc<Mutex<HashSet<String>>>,
}

/// The job a response is about, for the request log.
#[derive(Clone)]
struct JobTag(String);

fn tagged(mut r: Response, id: &str) -> Response {
    r.extensions_mut().insert(JobTag(id.to_string()));
    r
}

fn handler(r: &Route) -> Option<MethodRouter<App>> {
    Some(match (r.method, r.path) {
        ("GET", "/health") => get(health),
        ("GET", "/ready") => get(ready),
        ("GET", "/metrics") => get(metrics),
        ("GET", "/openapi.json") => get(openapi_json),
        ("POST", "/v1/reconstruct") => post(reconstruct).layer(DefaultBodyLimit::disable()),
        ("GET", "/v1/jobs/{id}") => get(job_get),
        ("DELETE", "/v1/jobs/{id}") => delete(job_delete),
        ("GET", "/v1/jobs/{id}/files/{path}") => get(job_file),
        ("GET", "/v1/jobs/{id}/archive") => get(job_archive),
        ("POST", "/v1/jobs/{id}/scene") => post(job_scene),
        ("GET", "/v1/jobs/{id}/scene/files/{path}") => get(scene_file),
        _ => return None,
    })
}

fn router(app: App) -> Router {
    let mut r: Router<App> = Router::new();
    for route in ROUTES {
        if let Some(h) = handler(route) {
            r = r.route(&axum_path(route.path), h);
        }
    }
    r.fallback(|| async { ApiError::not_found("no such route (GET /openapi.json lists them)") })
        .layer(from_fn_with_state(app.clone(), auth))
        .layer(from_fn_with_state(app.clone(), log_requests))
        .with_state(app)
}

/// Constant-time comparison (the token's length is not secret).
fn same(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

async fn auth(State(app): State<App>, req: Request, next: Next) -> Response {
    let Some(token) = app.jobs.cfg.token.as_ref() else { return next.run(req).await };
    if req.uri().path() == "/health" {
        return next.run(req).await;
    }
    let given = req.headers().get(header::AUTHORIZATION).and_then(|v| v.to_str().ok()).and_then(|v| v.strip_prefix("Bearer "));
    if given.is_some_and(|g| same(g.trim().as_bytes(), token.expose().as_bytes())) {
        return next.run(req).await;
    }
    // Unauthenticated bodies are drained only up to 1 MiB.
    linger(req.into_body(), 1 << 20);
    let mut r = ApiError::new(StatusCode::UNAUTHORIZED, "missing or wrong bearer token (Authorization: Bearer <token>)").into_response();
    r.headers_mut().insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
    r
}

/// One request's log line; written when the answer leaves, or, when the client went
/// away first, on drop with status 499 (client closed the request).
struct RequestLine {
    jobs: Arc<Jobs>,
    t0: Instant,
    method: String,
    path: String,
    answered: Option<(u16, Option<String>)>,
}

impl Drop for RequestLine {
    fn drop(&mut self) {
        let (status, job) = self.answered.take().unwrap_or((499, None));
        self.jobs.metrics.request(status);
        log(
            "request",
            serde_json::json!({
                "method": self.method, "path": self.path, "status": status, "job": job,
                "seconds": (self.t0.elapsed().as_secs_f64() * 1e4).round() / 1e4, "peak_rss_mib": peak_mib(),
            }),
        );
    }
}

async fn log_requests(State(app): State<App>, req: Request, next: Next) -> Response {
    let mut line = RequestLine {
        jobs: app.jobs.clone(),
        t0: Instant::now(),
        method: req.method().to_string(),
        path: req.uri().path().to_string(),
        answered: None,
    };
    let r = next.run(req).await;
    line.answered = Some((r.status().as_u16(), r.extensions().get::<JobTag>().map(|t| t.0.clone())));
    r
}

async fn health() -> Json<serde_json::Value> {
    Json(serde_json::json!({"status": "ok", "recon_version": recon_core::VERSION}))
}

fn is_ready(app: &App) -> (bool, &'static str) {
    if app.jobs.stopping() {
        (false, "shutting down")
    } else if app.jobs.waiting() >= app.jobs.cfg.queue {
        (false, "queue full")
    } else {
        (true, "model loaded, queue has room")
    }
}

async fn ready(State(app): State<App>) -> Response {
    let (ok, why) = is_ready(&app);
    let body = serde_json::json!({"ready": ok, "reason": why, "queued": app.jobs.waiting(), "running": app.jobs.running(),
        "queue": app.jobs.cfg.queue, "workers": app.jobs.cfg.workers.get(),
        "recon_version": recon_core::VERSION, "model_identity": app.jobs.engine.pipeline.identity()});
    (if ok { StatusCode::OK } else { StatusCode::SERVICE_UNAVAILABLE }, Json(body)).into_response()
}

async fn metrics(State(app): State<App>) -> Response {
    let text = app.jobs.metrics.render(app.jobs.waiting(), app.jobs.running(), is_ready(&app).0);
    ([(header::CONTENT_TYPE, "text/plain; version=0.0.4")], text).into_response()
}

async fn openapi_json() -> Json<serde_json::Value> {
    Json(openapi())
}

/// Reads and drops the rest of a request body in the background (at most `cap` bytes, 30
/// s), so that a client still sending it reads the early answer (401, 413, 429, 400)
/// instead of a broken pipe: a lingering close.
fn linger(body: Body, cap: u64) {
    tokio::spawn(async move {
        use http_body_util::BodyExt;
        let mut body = body;
        let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
        let mut n = 0u64;
        while let Ok(Some(Ok(frame))) = tokio::time::timeout_at(deadline, body.frame()).await {
            n += frame.data_ref().map_or(0, |d| d.len() as u64);
            if n > cap {
                break;
            }
        }
    });
}

/// [`linger`] for a multipart body an error stopped reading.
fn linger_multipart(mut mp: Multipart) {
    tokio::spawn(async move {
        let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
        while let Ok(Ok(Some(mut f))) = tokio::time::timeout_at(deadline, mp.next_field()).await {
            while let Ok(Ok(Some(_))) = tokio::time::timeout_at(deadline, f.chunk()).await {}
        }
    });
}

/// Removes a job folder whose upload did not end in a queued job.
struct DirGuard(Option<PathBuf>);

impl Drop for DirGuard {
    fn drop(&mut self) {
        if let Some(d) = self.0.take() {
            let _ = std::fs::remove_dir_all(d);
        }
    }
}

/// Cancels a `wait=true` job when its request is dropped before the answer (the client
/// went away).
struct CancelOnDrop {
    jobs: Arc<Jobs>,
    job: Option<Arc<Job>>,
}

impl Drop for CancelOnDrop {
    fn drop(&mut self) {
        if let Some(job) = self.job.take() {
            if !job.status().finished() {
                log("client_gone", serde_json::json!({"job": job.id}));
                self.jobs.cancel(&job, CancelReason::ClientGone);
            }
        }
    }
}

fn multipart_error(e: axum::extract::multipart::MultipartError, part: Option<&str>, limit: u64) -> ApiError {
    let part = part.unwrap_or("request");
    if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
        return ApiError::new(
            StatusCode::PAYLOAD_TOO_LARGE,
            format!("the upload is larger than the limit of {} bytes (--max-upload-mb)", limit),
        )
        .at(part, "bytes");
    }
    ApiError::bad(part, "multipart", format!("malformed multipart body: {}", e.body_text()))
}

/// Streams the multipart parts into `<job>/inputs/`; small parts are also kept in memory.
async fn receive(mp: &mut Multipart, dir: &std::path::Path, cfg: &ServeConfig) -> Result<(Manifest, BTreeMap<String, Vec<u8>>), ApiError> {
    let limit = cfg.max_upload_bytes;
    let mut m = Manifest::default();
    let mut small: BTreeMap<String, Vec<u8>> = BTreeMap::new();
    let mut total = 0u64;
    while let Some(mut field) = mp.next_field().await.map_err(|e| multipart_error(e, None, limit))? {
        let name = field.name().unwrap_or_default().to_string();
        inputs::check_part_name(&name)?;
        let count = m.parts.get(&name).map_or(0, Vec::len);
        if count > 0 && !is_repeatable(&name) {
            return Err(ApiError::bad(&name, "name", format!("part `{name}` given twice")));
        }
        // Each binary mask part is decoded at full size: their number is bounded up front.
        let max_objects = cfg.defaults.max_objects.get();
        if count >= max_objects {
            return Err(ApiError::new(
                StatusCode::PAYLOAD_TOO_LARGE,
                format!("more than {max_objects} {name} parts (objects per frame, --max-objects)"),
            )
            .at(&name, "count"));
        }
        let filename = field.file_name().and_then(inputs::safe_filename);
        let rel = if is_repeatable(&name) {
            let base = filename.clone().unwrap_or_else(|| format!("mask-{count}.png"));
            let taken = m.parts.get(&name).is_some_and(|v| v.iter().any(|p| p.file.ends_with(&format!("/{base}"))));
            let file = if taken { format!("{count}-{base}") } else { base };
            tokio::fs::create_dir_all(dir.join("inputs").join(&name))
                .await
                .map_err(|e| ApiError::unavailable(format!("storing {name}: {e}")))?;
            format!("inputs/{name}/{file}")
        } else {
            format!("inputs/{name}")
        };
        let path = dir.join(&rel);
        let mut f = tokio::fs::File::create(&path).await.map_err(|e| ApiError::unavailable(format!("storing {name}: {e}")))?;
        let mut bytes = 0u64;
        let mut keep = Vec::new();
        while let Some(chunk) = field.chunk().await.map_err(|e| multipart_error(e, Some(&name), limit))? {
            bytes += chunk.len() as u64;
            total += chunk.len() as u64;
            if total > limit {
                return Err(ApiError::new(
                    StatusCode::PAYLOAD_TOO_LARGE,
                    format!("the upload is larger than the limit of {limit} bytes (--max-upload-mb)"),
                )
                .at(&name, "bytes"));
            }
            if is_small_part(&name) {
                if bytes > MAX_SMALL_PART_BYTES {
                    return Err(ApiError::new(StatusCode::PAYLOAD_TOO_LARGE, format!("{name}: more than {MAX_SMALL_PART_BYTES} bytes"))
                        .at(&name, "bytes"));
                }
                keep.extend_from_slice(&chunk);
            }
            f.write_all(&chunk).await.map_err(|e| ApiError::unavailable(format!("storing {name}: {e}")))?;
        }
        f.flush().await.map_err(|e| ApiError::unavailable(format!("storing {name}: {e}")))?;
        if bytes == 0 {
            return Err(ApiError::bad(&name, "bytes", format!("part `{name}` is empty")));
        }
        if is_small_part(&name) {
            small.insert(name.clone(), keep);
        }
        m.parts.entry(name).or_default().push(StoredPart { file: rel, filename, bytes });
    }
    Ok((m, small))
}

fn parse_wait(q: &BTreeMap<String, String>) -> Result<bool, ApiError> {
    match q.get("wait").map(|s| s.as_str()) {
        None | Some("true") | Some("1") | Some("") => Ok(true),
        Some("false") | Some("0") => Ok(false),
        Some(v) => Err(ApiError::bad("wait", "wait", format!("wait must be true or false, got `{v}`"))),
    }
}

async fn reconstruct(State(app): State<App>, Query(q): Query<BTreeMap<String, String>>, req: Request) -> Result<Response, ApiError> {
    let cfg = &app.jobs.cfg;
    let limit = cfg.max_upload_bytes;
    let (head, body) = req.into_parts();
    let wait = match parse_wait(&q) {
        Ok(w) => w,
        Err(e) => {
            linger(body, limit);
            return Err(e);
        }
    };
    let claimed = head.headers.get(header::CONTENT_LENGTH).and_then(|v| v.to_str().ok()).and_then(|v| v.parse::<u64>().ok());
    if claimed.is_some_and(|n| n > limit) {
        return Err(ApiError::new(
            StatusCode::PAYLOAD_TOO_LARGE,
            format!("Content-Length {} is larger than the limit of {limit} bytes (--max-upload-mb)", claimed.unwrap_or(0)),
        )
        .at("request", "Content-Length"));
    }
    let Some(slot) = app.jobs.reserve() else {
        linger(body, limit);
        if app.jobs.stopping() {
            return Err(ApiError::unavailable("the server is shutting down"));
        }
        app.jobs.metrics.rejected_full();
        let mut e =
            ApiError::new(StatusCode::TOO_MANY_REQUESTS, format!("the queue is full ({} jobs waiting); try again later", cfg.queue));
        e.retry_after = Some(app.jobs.retry_after());
        return Err(e);
    };
    let req = Request::from_parts(head, Body::new(http_body_util_limited(body, limit)));
    let mut mp = Multipart::from_request(req, &app)
        .await
        .map_err(|e| ApiError::bad("request", "Content-Type", format!("expected a multipart/form-data body: {}", e.body_text())))?;
    let (id, dir) = app.jobs.create_dir()?;
    let mut guard = DirGuard(Some(dir.clone()));
    let (mut manifest, small) = match receive(&mut mp, &dir, cfg).await {
        Ok(r) => r,
        Err(e) => {
            linger_multipart(mp);
            return Err(e);
        }
    };
    manifest.options = inputs::merge_options(&cfg.defaults, small.get("options").map(|v| v.as_slice()))?;
    if let Some(o) = small.get("objects") {
        manifest.objects = Some(inputs::parse_objects(o)?);
    }
    // Everything recon infer would refuse is refused here, before the job is queued.
    let (check_dir, check_m, jobs) = (dir.clone(), manifest.clone(), app.jobs.clone());
    tokio::task::spawn_blocking(move || inputs::load(&check_dir, &check_m, jobs.engine.pipeline.max_views()).map(|_| ()))
        .await
        .map_err(|e| ApiError::unavailable(format!("checking the inputs: {e}")))??;
    let job = app.jobs.submit(slot, id.clone(), dir, &manifest)?;
    guard.0 = None;
    log("job", serde_json::json!({"job": id, "status": "queued"}));
    if !wait {
        let body = job_json(&job);
        let mut r = (StatusCode::ACCEPTED, Json(body)).into_response();
        if let Ok(v) = HeaderValue::from_str(&format!("/v1/jobs/{id}")) {
            r.headers_mut().insert(header::LOCATION, v);
        }
        return Ok(tagged(r, &id));
    }
    let mut cancel = CancelOnDrop { jobs: app.jobs.clone(), job: Some(job.clone()) };
    let mut rx = job.subscribe();
    let mut shut = app.shutdown.clone();
    let mut shutdown_seen = *shut.borrow();
    loop {
        let status = *rx.borrow_and_update();
        if status.finished() {
            break;
        }
        if shutdown_seen && status == Status::Queued {
            cancel.job = None;
            return Err(ApiError::unavailable(format!(
                "the server is shutting down; job {id} stays queued and runs after the restart (GET /v1/jobs/{id})"
            )));
        }
        tokio::select! {
            r = rx.changed() => if r.is_err() { break },
            r = shut.changed(), if !shutdown_seen => { shutdown_seen = r.is_err() || *shut.borrow(); }
        }
    }
    cancel.job = None;
    Ok(tagged(finished_response(&job), &id))
}

/// A body that errors (413 through multer) once more than `limit` bytes arrive.
fn http_body_util_limited(b: Body, limit: u64) -> http_body_util::Limited<Body> {
    http_body_util::Limited::new(b, usize::try_from(limit).unwrap_or(usize::MAX))
}

/// The answer to a finished `wait=true` job: the job document, with the HTTP status its
/// outcome calls for.
fn finished_response(job: &Job) -> Response {
    let r = job.record();
    let code = match (r.status, r.error.as_ref().map(|e| e.reason.as_str())) {
        (Status::Done, _) => StatusCode::OK,
        (Status::Cancelled, _) => StatusCode::CONFLICT,
        (_, Some("timeout")) => StatusCode::GATEWAY_TIMEOUT,
        (_, Some("input")) | (_, Some("error")) => StatusCode::UNPROCESSABLE_ENTITY,
        _ => StatusCode::SERVICE_UNAVAILABLE,
    };
    (code, Json(job_json(job))).into_response()
}

fn job_json(job: &Job) -> serde_json::Value {
    let r = job.record();
    let mut v = serde_json::to_value(&r).unwrap_or_default();
    v["urls"] = serde_json::json!({
        "self": format!("/v1/jobs/{}", r.id),
        "archive": (r.status == Status::Done).then(|| format!("/v1/jobs/{}/archive", r.id)),
        "scene": (r.status == Status::Done).then(|| format!("/v1/jobs/{}/scene", r.id)),
    });
    v
}

fn find_job(app: &App, id: &str) -> Result<Arc<Job>, ApiError> {
    if !valid_id(id) {
        return Err(ApiError::not_found(format!("no job `{id}`")).at("id", "id"));
    }
    app.jobs.get(id).ok_or_else(|| ApiError::not_found(format!("no job {id}")).at("id", "id"))
}

fn done_job(app: &App, id: &str) -> Result<Arc<Job>, ApiError> {
    let job = find_job(app, id)?;
    let s = job.status();
    if s != Status::Done {
        return Err(ApiError::new(StatusCode::CONFLICT, format!("job {id} is {}; its files are served once it is done", s.name()))
            .at("id", "status"));
    }
    Ok(job)
}

async fn job_get(State(app): State<App>, UrlPath(id): UrlPath<String>) -> Result<Response, ApiError> {
    let job = find_job(&app, &id)?;
    Ok(tagged(Json(job_json(&job)).into_response(), &id))
}

async fn job_delete(State(app): State<App>, UrlPath(id): UrlPath<String>) -> Result<Response, ApiError> {
    let job = find_job(&app, &id)?;
    if job.status().finished() {
        let jobs = app.jobs.clone();
        let j = job.clone();
        tokio::task::spawn_blocking(move || jobs.delete(&j)).await.map_err(|e| ApiError::unavailable(e.to_string()))??;
        return Ok(tagged(Json(serde_json::json!({"id": id, "deleted": true})).into_response(), &id));
    }
    let status = app.jobs.cancel(&job, CancelReason::User);
    let (code, msg) = if status.finished() {
        (StatusCode::OK, "cancelled")
    } else {
        (StatusCode::ACCEPTED, "cancel requested: the job stops at its next stage boundary (GET it to see it end)")
    };
    let mut body = job_json(&job);
    body["message"] = serde_json::json!(msg);
    Ok(tagged((code, Json(body)).into_response(), &id))
}

async fn serve_file(root: PathBuf, rel: &str, id: &str) -> Result<Response, ApiError> {
    let Some(path) = paths::resolve(&root, rel) else {
        return Err(ApiError::not_found(format!("no file `{rel}` in job {id}")).at("path", "path"));
    };
    let bytes = tokio::fs::read(&path).await.map_err(|_| ApiError::not_found(format!("no file `{rel}` in job {id}")).at("path", "path"))?;
    Ok(tagged(([(header::CONTENT_TYPE, paths::content_type(&path))], bytes).into_response(), id))
}

async fn job_file(State(app): State<App>, UrlPath((id, rel)): UrlPath<(String, String)>) -> Result<Response, ApiError> {
    let job = done_job(&app, &id)?;
    serve_file(job.dir.join("out"), &rel, &id).await
}

async fn scene_file(State(app): State<App>, UrlPath((id, rel)): UrlPath<(String, String)>) -> Result<Response, ApiError> {
    let job = done_job(&app, &id)?;
    let root = job.dir.join("scene");
    if !root.join(recon_sim::MARKER).is_file() {
        return Err(ApiError::not_found(format!("job {id} has no scene yet (POST /v1/jobs/{id}/scene)")).at("path", "path"));
    }
    serve_file(root, &rel, &id).await
}

async fn job_archive(State(app): State<App>, UrlPath(id): UrlPath<String>) -> Result<Response, ApiError> {
    let job = done_job(&app, &id)?;
    let out = job.dir.join("out");
    let bytes = tokio::task::spawn_blocking(move || zip_folder(&out))
        .await
        .map_err(|e| ApiError::unavailable(e.to_string()))?
        .map_err(|e| ApiError::unavailable(format!("building the archive: {e}")))?;
    let disposition = format!("attachment; filename=\"{id}.zip\"");
    let mut r = ([(header::CONTENT_TYPE, "application/zip")], bytes).into_response();
    if let Ok(v) = HeaderValue::from_str(&disposition) {
        r.headers_mut().insert(header::CONTENT_DISPOSITION, v);
    }
    Ok(tagged(r, &id))
}

/// Every regular file under `root` in a zip (stored: meshes and PLYs barely compress).
fn zip_folder(root: &std::path::Path) -> Result<Vec<u8>, String> {
    use std::io::Write;
    let mut w = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let opts = zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored).large_file(true);
    for rel in paths::list_files(root) {
        let bytes = std::fs::read(root.join(&rel)).map_err(|e| format!("{rel}: {e}"))?;
        w.start_file(rel.as_str(), opts).map_err(|e| e.to_string())?;
        w.write_all(&bytes).map_err(|e| e.to_string())?;
    }
    Ok(w.finish().map_err(|e| e.to_string())?.into_inner())
}

async fn job_scene(State(app): State<App>, UrlPath(id): UrlPath<String>, body: axum::body::Bytes) -> Result<Response, ApiError> {
    let job = done_job(&app, &id)?;
    let opts = if body.iter().all(u8::is_ascii_whitespace) {
        serde_json::json!({})
    } else {
        serde_json::from_slice(&body).map_err(|e| ApiError::bad("body", "json", format!("scene options: invalid JSON: {e}")))?
    };
    let opts = recon_sim::SceneOptions::from_json(opts)
        .map_err(|e| ApiError::bad("body", e.option(), format!("scene options: {}", e.keyword_message())))?;
    if !app.scenes.lock().unwrap_or_else(PoisonError::into_inner).insert(id.clone()) {
        return Err(ApiError::new(StatusCode::CONFLICT, format!("a scene of job {id} is being built")).at("id", "scene"));
    }
    let (jobs, j, scenes, key) = (app.jobs.clone(), job.clone(), app.scenes.clone(), id.clone());
    let r = tokio::task::spawn_blocking(move || {
        let r = build_scene(&jobs, &j, &opts);
        scenes.lock().unwrap_or_else(PoisonError::into_inner).remove(&key);
        r
    })
    .await
    .map_err(|e| ApiError::unavailable(e.to_string()))??;
    Ok(tagged(Json(r).into_response(), &id))
}

/// `recon scene` on a finished job's output folder and its stored frame, into `<job>/scene`.
fn build_scene(jobs: &Jobs, job: &Job, opts: &recon_sim::SceneOptions) -> Result<serde_json::Value, ApiError> {
    let m: Manifest = std::fs::read(job.dir.join("request.json"))
        .ok()
        .and_then(|b| serde_json::from_slice(&b).ok())
        .ok_or_else(|| ApiError::unavailable("the stored request is unreadable"))?;
    let loaded = inputs::load(&job.dir, &m, jobs.engine.pipeline.max_views())?;
    let settings = opts.settings().map_err(|e| ApiError::bad("body", e.option(), e.keyword_message()))?;
    let table = recon_sim::MaterialTable::builtin();
    let out = job.dir.join("out");
    let unprocessable =
        |e: recon_core::Error| ApiError::new(StatusCode::UNPROCESSABLE_ENTITY, format!("recon scene: {e}")).at("id", "scene");
    let (scene, notes) = recon_sim::scene_from_infer_output(&out, &loaded.frame, &table, &opts.plane_fit()).map_err(unprocessable)?;
    let file = out.join(recon_core::engine::MARKER).display().to_string();
    let mut sim = recon_sim::build_scene(&scene, &table, &settings, &file).map_err(unprocessable)?;
    let dir = job.dir.join("scene");
    recon_sim::write_outputs(&mut sim, &dir).map_err(|e| ApiError::unavailable(format!("writing the scene: {e}")))?;
    let files: Vec<String> = paths::list_files(&dir).into_iter().map(|f| format!("/v1/jobs/{}/scene/files/{f}", job.id)).collect();
    Ok(serde_json::json!({
        "job": job.id,
        "objects": sim.summaries(),
        "at_rest": sim.settle.at_rest,
        "notes": notes,
        "files": files,
    }))
}

/// A server that is listening; [`RunningServer::shutdown`] stops it gracefully.
pub struct RunningServer {
    addr: SocketAddr,
    jobs: Arc<Jobs>,
    stop: watch::Sender<bool>,
    http: tokio::task::JoinHandle<std::io::Result<()>>,
    sweeper: tokio::task::JoinHandle<()>,
}

impl RunningServer {
    /// The address it listens on (the port chosen, with `--bind …:0`).
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// Graceful shutdown: stops accepting requests and queued jobs (they stay queued on
    /// disk and run after a restart), lets running jobs finish within the grace period,
    /// then stops them (`failed: interrupted`) and returns once the requests in flight are
    /// answered.
    pub async fn shutdown(self) -> Result<(), ServeError> {
        let t0 = Instant::now();
        let grace = self.jobs.cfg.shutdown_grace;
        log("shutdown", serde_json::json!({"running": self.jobs.running(), "queued": self.jobs.waiting(), "grace_s": grace.as_secs_f64()}));
        self.jobs.stop_taking();
        let _ = self.stop.send(true);
        self.sweeper.abort();
        while self.jobs.running() > 0 && t0.elapsed() < grace {
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        if self.jobs.running() > 0 {
            self.jobs.interrupt_running();
            let t1 = Instant::now();
            while self.jobs.running() > 0 && t1.elapsed() < Duration::from_secs(60) {
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
        }
        let http = tokio::time::timeout(Duration::from_secs(10), self.http).await;
        log("stopped", serde_json::json!({"seconds": t0.elapsed().as_secs_f64(), "running": self.jobs.running()}));
        match http {
            Ok(Ok(Err(e))) => Err(ServeError::io("http server", e)),
            _ => Ok(()),
        }
    }
}

/// Starts the server on the current tokio runtime: checks the settings, opens the data
/// folder (recovering its jobs), starts the workers and listens.
pub async fn start(cfg: ServeConfig, engine: Arc<Engine>) -> Result<RunningServer, ServeError> {
    cfg.check()?;
    let bind = cfg.bind;
    let keep = cfg.keep;
    let jobs = tokio::task::spawn_blocking(move || Jobs::open(cfg, engine))
        .await
        .map_err(|e| ServeError::config("--data-dir", e.to_string()))??;
    let listener = tokio::net::TcpListener::bind(bind).await.map_err(|source| ServeError::Bind { addr: bind, source })?;
    let addr = listener.local_addr().map_err(|source| ServeError::Bind { addr: bind, source })?;
    jobs.start_workers()?;
    let (stop, shutdown) = watch::channel(false);
    let app = App { jobs: jobs.clone(), shutdown: shutdown.clone(), scenes: Arc::new(Mutex::new(HashSet::new())) };
    let mut stopped = shutdown.clone();
    let http = tokio::spawn(async move {
        axum::serve(listener, router(app))
            .with_graceful_shutdown(async move {
                let _ = stopped.wait_for(|s| *s).await;
            })
            .await
    });
    let sweep_jobs = jobs.clone();
    let sweeper = tokio::spawn(async move {
        let Some(keep) = keep else { return };
        let every = (keep / 4).clamp(Duration::from_millis(200), Duration::from_secs(60));
        loop {
            let j = sweep_jobs.clone();
            let _ = tokio::task::spawn_blocking(move || j.sweep()).await;
            tokio::time::sleep(every).await;
        }
    });
    log(
        "listening",
        serde_json::json!({"addr": addr.to_string(), "workers": jobs.cfg.workers.get(), "queue": jobs.cfg.queue,
            "data_dir": jobs.cfg.data_dir, "auth": jobs.cfg.token.is_some(), "max_upload_bytes": jobs.cfg.max_upload_bytes}),
    );
    Ok(RunningServer { addr, jobs, stop, http, sweeper })
}

/// Runs the server until SIGTERM or SIGINT, then shuts it down gracefully; blocks (the
/// server's own tokio runtime: a few threads for the I/O, the workers run the engine on
/// threads of their own). `on_listening` hears the address once it listens.
pub fn run(cfg: ServeConfig, engine: Arc<Engine>, on_listening: impl FnOnce(SocketAddr)) -> Result<(), ServeError> {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .thread_name("recon-http")
        .enable_all()
        .build()
        .map_err(|e| ServeError::io("tokio runtime", e))?;
    rt.block_on(async move {
        let server = start(cfg, engine).await?;
        on_listening(server.addr());
        let mut term =
            tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()).map_err(|e| ServeError::io("SIGTERM handler", e))?;
        tokio::select! {
            _ = tokio::signal::ctrl_c() => log("signal", serde_json::json!({"signal": "SIGINT"})),
            _ = term.recv() => log("signal", serde_json::json!({"signal": "SIGTERM"})),
        }
        server.shutdown().await
    })
}
