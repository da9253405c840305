//! Jobs: their folders and state on disk, the queue, the workers that run them on the
//! shared engine, cancellation, recovery after a restart and retention.
//!
//! **A job folder** (`<data-dir>/jobs/<id>/`): `inputs/` (the parts as received),
//! `request.json` (which parts, the options), `state.json` (status, stage, result; always
//! replaced atomically: written beside, synced, renamed), `out/` (exactly what `recon
//! infer` writes; written into `out.partial` and renamed, by the engine's output writer),
//! `scene/` (`recon scene`'s output, when asked for). A folder without `state.json` is an
//! upload that never finished.
//!
//! **After a crash or `kill -9`**, at start: folders without `state.json` are removed;
//! `queued` jobs are queued again (their inputs are complete: they were checked before
//! the job was accepted); `running` jobs are reported `failed` with reason `interrupted`
//! and are not re-run, since a job that took the server down could do it again; the
//! client may submit them again. `done` jobs are served as they were: their state says
//! done only after `out/` was renamed into place.
//!
//! **Cancellation**: a queued job leaves the queue at once. A running one stops at the
//! engine's next progress event (a new object, sample or model stage, decimation or
//! selection): the engine has no cancellation hook, so the worker's progress callback
//! unwinds out of the engine with a private payload, which the worker catches. A sampler
//! loop in progress is not interrupted (a stage of the default model takes well under a
//! second on 2 cores; of recgen-large, minutes).

use crate::config::ServeConfig;
use crate::error::{ApiError, ServeError};
use crate::inputs::{self, Manifest};
use crate::log::{log, now_unix, peak_mib};
use crate::metrics::Metrics;
use recon_core::engine::{
    stage_seconds, write_outputs, Engine, FrameResult, ModelIdentity, Progress, SecondView, WrittenObject, STAGE_COLUMNS,
};
use serde::{Deserialize, Serialize};
use std::collections::{HashMap, VecDeque};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU8, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex, PoisonError};
use std::time::{Duration, Instant};
use tokio::sync::watch;

/// A job's status.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Status {
    /// Accepted, waiting for a worker.
    Queued,
    /// A worker runs it.
    Running,
    /// Finished; its files are served.
    Done,
    /// Stopped by an error, a timeout or an interruption (`error.reason` says which).
    Failed,
    /// Cancelled by `DELETE` or by its client disconnecting.
    Cancelled,
}

impl Status {
    /// Whether the job will not change any more.
    pub fn finished(self) -> bool {
        matches!(self, Status::Done | Status::Failed | Status::Cancelled)
    }

    /// The lower-case name (`queued`).
    pub fn name(self) -> &'static str {
        match self {
            Status::Queued => "queued",
            Status::Running => "running",
            Status::Done => "done",
            Status::Failed => "failed",
            Status::Cancelled => "cancelled",
        }
    }
}

/// Why a job failed or was cancelled.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JobError {
    /// `input`, `error`, `write`, `timeout`, `interrupted`, `cancelled`, `client disconnected`.
    pub reason: String,
    /// What happened, in words.
    pub message: String,
}

/// A job's state, as `state.json` holds it and `GET /v1/jobs/{id}` answers.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct JobRecord {
    /// The job id (32 hex digits).
    pub id: String,
    /// Its status.
    pub status: Status,
    /// When it was accepted (Unix seconds).
    pub created_unix: f64,
    /// When a worker started it.
    pub started_unix: Option<f64>,
    /// When it finished.
    pub finished_unix: Option<f64>,
    /// The engine's current stage while running (`ss sampling`, `decimating`, …).
    pub stage: Option<String>,
    /// The object being reconstructed (`id 8 [1/3]`).
    pub object: Option<String>,
    /// Fraction done, 0 to 1 (objects, samples and model stages).
    pub progress: f64,
    /// Why it failed or was cancelled.
    pub error: Option<JobError>,
    /// The answer when done (objects, poses, file URLs).
    pub result: Option<serde_json::Value>,
}

/// Who asked a running job to stop.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub enum CancelReason {
    /// `DELETE /v1/jobs/{id}`.
    User = 1,
    /// The client of a `wait=true` request went away.
    ClientGone = 2,
    /// `--job-timeout-s` passed.
    Timeout = 3,
    /// The server shut down and the grace period ended.
    Shutdown = 4,
}

impl CancelReason {
    fn from_u8(v: u8) -> Option<Self> {
        match v {
            1 => Some(CancelReason::User),
            2 => Some(CancelReason::ClientGone),
            3 => Some(CancelReason::Timeout),
            4 => Some(CancelReason::Shutdown),
            _ => None,
        }
    }

    /// The status and error a job stopped for this reason ends with.
    fn outcome(self, timeout: Option<Duration>) -> (Status, JobError) {
        let e = |r: &str, m: String| JobError { reason: r.into(), message: m };
        match self {
            CancelReason::User => (Status::Cancelled, e("cancelled", "cancelled by DELETE /v1/jobs/{id}".into())),
            CancelReason::ClientGone => {
                (Status::Cancelled, e("client disconnected", "the client of the wait=true request disconnected".into()))
            }
            CancelReason::Timeout => {
                (Status::Failed, e("timeout", format!("ran longer than --job-timeout-s {:.0} s", timeout.map_or(0.0, |t| t.as_secs_f64()))))
            }
            CancelReason::Shutdown => {
                (Status::Failed, e("interrupted", "the server shut down before the job finished (grace period over)".into()))
            }
        }
    }
}

/// The payload a cancelled job unwinds out of the engine with.
struct Cancelled;

/// Silences the panic message of [`Cancelled`] unwinds (once per process); every other
/// panic is reported by the previous hook as before.
fn quiet_cancel_unwinds() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        let prev = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if !info.payload().is::<Cancelled>() {
                prev(info)
            }
        }));
    });
}

/// One job in memory.
pub struct Job {
    /// The id.
    pub id: String,
    /// Its folder.
    pub dir: PathBuf,
    record: Mutex<JobRecord>,
    cancel: AtomicU8,
    tx: watch::Sender<Status>,
}

impl Job {
    fn new(id: String, dir: PathBuf, record: JobRecord) -> Arc<Self> {
        let (tx, _) = watch::channel(record.status);
        Arc::new(Job { id, dir, record: Mutex::new(record), cancel: AtomicU8::new(0), tx })
    }

    /// A copy of the state.
    pub fn record(&self) -> JobRecord {
        self.record.lock().unwrap_or_else(PoisonError::into_inner).clone()
    }

    /// The status.
    pub fn status(&self) -> Status {
        self.record.lock().unwrap_or_else(PoisonError::into_inner).status
    }

    /// Watches the status (for `wait=true`).
    pub fn subscribe(&self) -> watch::Receiver<Status> {
        self.tx.subscribe()
    }

    fn update(&self, f: impl FnOnce(&mut JobRecord)) {
        f(&mut self.record.lock().unwrap_or_else(PoisonError::into_inner));
    }

    /// Changes the state, writes it atomically, then tells the watchers.
    fn transition(&self, f: impl FnOnce(&mut JobRecord)) -> std::io::Result<()> {
        let (status, text) = {
            let mut r = self.record.lock().unwrap_or_else(PoisonError::into_inner);
            f(&mut r);
            (r.status, serde_json::to_vec_pretty(&*r).map_err(std::io::Error::other)?)
        };
        let res = write_atomic(&self.dir.join("state.json"), &text);
        self.tx.send_replace(status);
        res
    }

    /// Asks the job to stop; the first reason wins. Returns whether this call set it.
    pub fn request_cancel(&self, why: CancelReason) -> bool {
        self.cancel.compare_exchange(0, why as u8, Ordering::SeqCst, Ordering::SeqCst).is_ok()
    }

    fn cancel_reason(&self) -> Option<CancelReason> {
        CancelReason::from_u8(self.cancel.load(Ordering::SeqCst))
    }
}

/// Writes `bytes` to `path` atomically: a temporary file beside it, synced, renamed over
/// it, and the folder synced, so a crash leaves the old or the new content.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    use std::io::Write;
    let tmp = path.with_extension("tmp");
    {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
    }
    std::fs::rename(&tmp, path)?;
    if let Some(dir) = path.parent() {
        if let Ok(d) = std::fs::File::open(dir) {
            let _ = d.sync_all();
        }
    }
    Ok(())
}

/// A new job id: 128 bits from the operating system's generator, as 32 hex digits.
pub fn new_id() -> Result<String, ApiError> {
    let mut b = [0u8; 16];
    getrandom::fill(&mut b).map_err(|e| ApiError::unavailable(format!("no random job id: {e}")))?;
    Ok(b.iter().map(|x| format!("{x:02x}")).collect())
}

/// Whether `s` has the form of a job id (so that it may name a folder).
pub fn valid_id(s: &str) -> bool {
    s.len() == 32 && s.bytes().all(|c| c.is_ascii_digit() || (b'a'..=b'f').contains(&c))
}

/// A place in the queue held by a request while it uploads; given back when dropped
/// unless the job was queued.
pub struct Slot {
    jobs: Arc<Jobs>,
    held: bool,
}

impl Drop for Slot {
    fn drop(&mut self) {
        if self.held {
            self.jobs.waiting.fetch_sub(1, Ordering::SeqCst);
        }
    }
}

/// Every job of this server, the queue and the workers.
pub struct Jobs {
    /// The settings.
    pub cfg: ServeConfig,
    /// The model, loaded once, shared by the workers.
    pub engine: Arc<Engine>,
    /// Counters for `/metrics`.
    pub metrics: Metrics,
    root: PathBuf,
    table: Mutex<HashMap<String, Arc<Job>>>,
    queue: Mutex<VecDeque<Arc<Job>>>,
    cv: Condvar,
    /// Queued jobs plus uploads holding a [`Slot`].
    waiting: AtomicUsize,
    running: AtomicUsize,
    stopping: AtomicBool,
    /// Mean seconds of a job (exponential average), for `Retry-After`.
    mean_job_s: Mutex<f64>,
}

impl Jobs {
    /// Opens the data folder and recovers its jobs (module docs).
    pub fn open(cfg: ServeConfig, engine: Arc<Engine>) -> Result<Arc<Self>, ServeError> {
        quiet_cancel_unwinds();
        let root = cfg.data_dir.join("jobs");
        std::fs::create_dir_all(&root).map_err(|e| ServeError::io(&root, e))?;
        let jobs = Arc::new(Jobs {
            cfg,
            engine,
            metrics: Metrics::default(),
            root,
            table: Mutex::new(HashMap::new()),
            queue: Mutex::new(VecDeque::new()),
            cv: Condvar::new(),
            waiting: AtomicUsize::new(0),
            running: AtomicUsize::new(0),
            stopping: AtomicBool::new(false),
            mean_job_s: Mutex::new(10.0),
        });
        jobs.recover()?;
        Ok(jobs)
    }

    fn recover(&self) -> Result<(), ServeError> {
        let entries = std::fs::read_dir(&self.root).map_err(|e| ServeError::io(&self.root, e))?;
        let (mut requeued, mut interrupted, mut removed, mut kept) = (0, 0, 0, 0);
        let mut queued = Vec::new();
        for entry in entries.flatten() {
            let dir = entry.path();
            let name = entry.file_name().to_string_lossy().to_string();
            if name.strip_prefix("deleting-").is_some_and(valid_id) && dir.is_dir() {
                // A deletion the previous run did not finish.
                let _ = std::fs::remove_dir_all(&dir);
                continue;
            }
            if !valid_id(&name) || !dir.is_dir() {
                continue;
            }
            let state = dir.join("state.json");
            let record: Option<JobRecord> = std::fs::read(&state).ok().and_then(|b| serde_json::from_slice(&b).ok());
            let Some(mut record) = record.filter(|r| r.id == name) else {
                // An upload that never finished (or a state no writer of this server made).
                let _ = std::fs::remove_dir_all(&dir);
                removed += 1;
                continue;
            };
            // Leftovers of an interrupted write are never served.
            for partial in ["out.partial", "scene.partial", "state.tmp"] {
                let p = dir.join(partial);
                let _ = if p.is_dir() { std::fs::remove_dir_all(&p) } else { std::fs::remove_file(&p) };
            }
            match record.status {
                Status::Running => {
                    record.status = Status::Failed;
                    record.finished_unix = Some(now_unix());
                    record.stage = None;
                    record.error = Some(JobError {
                        reason: "interrupted".into(),
                        message: "the server stopped while this job was running (crash, kill or shutdown); its inputs are kept, submit it again to re-run it".into(),
                    });
                    let text = serde_json::to_vec_pretty(&record).map_err(|e| ServeError::config("state.json", e.to_string()))?;
                    write_atomic(&state, &text).map_err(|e| ServeError::io(&state, e))?;
                    self.metrics.finished("failed");
                    interrupted += 1;
                }
                Status::Queued => {
                    queued.push((record.created_unix, name.clone()));
                    requeued += 1;
                }
                _ => kept += 1,
            }
            let job = Job::new(name.clone(), dir, record);
            self.table.lock().unwrap_or_else(PoisonError::into_inner).insert(name, job);
        }
        // Queued again in the order they were accepted.
        queued.sort_by(|a, b| a.0.total_cmp(&b.0));
        let table = self.table.lock().unwrap_or_else(PoisonError::into_inner);
        let mut q = self.queue.lock().unwrap_or_else(PoisonError::into_inner);
        for (_, id) in queued {
            if let Some(j) = table.get(&id) {
                q.push_back(j.clone());
                self.waiting.fetch_add(1, Ordering::SeqCst);
            }
        }
        log(
            "recovered",
            serde_json::json!({"requeued": requeued, "interrupted": interrupted, "incomplete_removed": removed, "finished": kept}),
        );
        Ok(())
    }

    /// Holds a place in the queue, or `None` when it is full (or the server stops).
    pub fn reserve(self: &Arc<Self>) -> Option<Slot> {
        if self.stopping.load(Ordering::SeqCst) {
            return None;
        }
        let cap = self.cfg.queue;
        self.waiting.fetch_update(Ordering::SeqCst, Ordering::SeqCst, |w| (w < cap).then_some(w + 1)).ok()?;
        Some(Slot { jobs: self.clone(), held: true })
    }

    /// Seconds a client refused for a full queue should wait: about one job's time.
    pub fn retry_after(&self) -> u64 {
        let m = *self.mean_job_s.lock().unwrap_or_else(PoisonError::into_inner);
        (m.ceil() as u64).clamp(1, 600)
    }

    /// Jobs waiting (queued, and uploads holding a place).
    pub fn waiting(&self) -> usize {
        self.waiting.load(Ordering::SeqCst)
    }

    /// Jobs running.
    pub fn running(&self) -> usize {
        self.running.load(Ordering::SeqCst)
    }

    /// Whether the server is shutting down.
    pub fn stopping(&self) -> bool {
        self.stopping.load(Ordering::SeqCst)
    }

    /// A fresh job folder with its `inputs/`: `(id, folder)`.
    pub fn create_dir(&self) -> Result<(String, PathBuf), ApiError> {
        for _ in 0..4 {
            let id = new_id()?;
            let dir = self.root.join(&id);
            match std::fs::create_dir(&dir) {
                Ok(()) => {
                    std::fs::create_dir(dir.join("inputs")).map_err(|e| ApiError::unavailable(format!("creating the job folder: {e}")))?;
                    return Ok((id, dir));
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
                Err(e) => return Err(ApiError::unavailable(format!("creating the job folder: {e}"))),
            }
        }
        Err(ApiError::unavailable("no free job id"))
    }

    /// Queues a job whose inputs are stored and checked; its [`Slot`] passes to the queue.
    pub fn submit(&self, mut slot: Slot, id: String, dir: PathBuf, manifest: &Manifest) -> Result<Arc<Job>, ApiError> {
        let text = serde_json::to_vec_pretty(manifest).map_err(|e| ApiError::unavailable(e.to_string()))?;
        write_atomic(&dir.join("request.json"), &text).map_err(|e| ApiError::unavailable(format!("storing the request: {e}")))?;
        let record = JobRecord {
            id: id.clone(),
            status: Status::Queued,
            created_unix: now_unix(),
            started_unix: None,
            finished_unix: None,
            stage: None,
            object: None,
            progress: 0.0,
            error: None,
            result: None,
        };
        let job = Job::new(id.clone(), dir, record);
        job.transition(|_| {}).map_err(|e| ApiError::unavailable(format!("storing the job state: {e}")))?;
        self.table.lock().unwrap_or_else(PoisonError::into_inner).insert(id, job.clone());
        self.queue.lock().unwrap_or_else(PoisonError::into_inner).push_back(job.clone());
        slot.held = false;
        self.metrics.accepted();
        self.cv.notify_one();
        Ok(job)
    }

    /// The job with this id.
    pub fn get(&self, id: &str) -> Option<Arc<Job>> {
        self.table.lock().unwrap_or_else(PoisonError::into_inner).get(id).cloned()
    }

    /// Cancels a job: a queued one at once, a running one at its next stage boundary.
    /// Returns its status after the call.
    pub fn cancel(&self, job: &Arc<Job>, why: CancelReason) -> Status {
        let removed = {
            let mut q = self.queue.lock().unwrap_or_else(PoisonError::into_inner);
            match q.iter().position(|j| Arc::ptr_eq(j, job)) {
                Some(i) => {
                    q.remove(i);
                    self.waiting.fetch_sub(1, Ordering::SeqCst);
                    true
                }
                None => false,
            }
        };
        if removed {
            let (status, err) = why.outcome(self.cfg.job_timeout);
            self.finish(job, status, Some(err), None, 0.0);
            return status;
        }
        if !job.status().finished() {
            job.request_cancel(why);
        }
        job.status()
    }

    /// Deletes a finished job's folder: renamed out of the way first (atomic, so the job's
    /// files are gone at once and never half-deleted under its id), then forgotten, then
    /// removed. A leftover `deleting-<id>` folder is removed at the next start.
    pub fn delete(&self, job: &Arc<Job>) -> Result<(), ApiError> {
        let gone = self.root.join(format!("deleting-{}", job.id));
        std::fs::rename(&job.dir, &gone).map_err(|e| ApiError::unavailable(format!("deleting the job folder: {e}")))?;
        self.table.lock().unwrap_or_else(PoisonError::into_inner).remove(&job.id);
        std::fs::remove_dir_all(&gone).map_err(|e| ApiError::unavailable(format!("deleting the job folder: {e}")))
    }

    /// Starts the workers (threads of their own: the engine's compute never runs on the
    /// async executor).
    pub fn start_workers(self: &Arc<Self>) -> Result<Vec<std::thread::JoinHandle<()>>, ServeError> {
        (0..self.cfg.workers.get())
            .map(|k| {
                let jobs = self.clone();
                std::thread::Builder::new()
                    .name(format!("recon-worker-{k}"))
                    .stack_size(8 << 20)
                    .spawn(move || jobs.work())
                    .map_err(|e| ServeError::io("worker thread", e))
            })
            .collect()
    }

    fn work(&self) {
        loop {
            let job = {
                let mut q = self.queue.lock().unwrap_or_else(PoisonError::into_inner);
                loop {
                    if self.stopping.load(Ordering::SeqCst) {
                        return;
                    }
                    if let Some(j) = q.pop_front() {
                        self.waiting.fetch_sub(1, Ordering::SeqCst);
                        self.running.fetch_add(1, Ordering::SeqCst);
                        break j;
                    }
                    q = self.cv.wait(q).unwrap_or_else(PoisonError::into_inner);
                }
            };
            // Whatever happens inside, the worker lives on and the job ends in a final state.
            let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| self.run(&job)));
            if r.is_err() {
                self.finish(&job, Status::Failed, Some(JobError { reason: "error".into(), message: "internal error".into() }), None, 0.0);
            }
            self.running.fetch_sub(1, Ordering::SeqCst);
        }
    }

    /// Stops the workers taking queued jobs (queued ones stay queued on disk and run after
    /// a restart) and refuses new ones.
    pub fn stop_taking(&self) {
        self.stopping.store(true, Ordering::SeqCst);
        let _q = self.queue.lock().unwrap_or_else(PoisonError::into_inner);
        self.cv.notify_all();
    }

    /// Asks every running job to stop (after the shutdown grace period).
    pub fn interrupt_running(&self) {
        for j in self.table.lock().unwrap_or_else(PoisonError::into_inner).values() {
            if j.status() == Status::Running {
                j.request_cancel(CancelReason::Shutdown);
            }
        }
    }

    /// Deletes finished jobs older than `--keep-hours`; returns how many.
    pub fn sweep(&self) -> usize {
        let Some(keep) = self.cfg.keep else { return 0 };
        let cutoff = now_unix() - keep.as_secs_f64();
        let old: Vec<Arc<Job>> = self
            .table
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .values()
            .filter(|j| {
                let r = j.record();
                r.status.finished() && r.finished_unix.unwrap_or(r.created_unix) < cutoff
            })
            .cloned()
            .collect();
        let n = old.iter().filter(|j| self.delete(j).is_ok()).count();
        if n > 0 {
            log("retention", serde_json::json!({"deleted": n}));
        }
        n
    }

    fn finish(&self, job: &Job, status: Status, error: Option<JobError>, result: Option<serde_json::Value>, seconds: f64) {
        let res = job.transition(|r| {
            r.status = status;
            r.finished_unix = Some(now_unix());
            r.stage = None;
            if status == Status::Done {
                r.progress = 1.0;
            }
            r.error = error.clone();
            r.result = result;
        });
        if let Err(e) = res {
            // The state could not be stored: the job is failed in memory, never done.
            job.update(|r| {
                r.status = Status::Failed;
                r.result = None;
                r.error = Some(JobError { reason: "write".into(), message: format!("storing the job state: {e}") });
            });
            job.tx.send_replace(Status::Failed);
        }
        let status = job.status();
        self.metrics.finished(status.name());
        log(
            "job",
            serde_json::json!({
                "job": job.id, "status": status.name(), "seconds": (seconds * 1e3).round() / 1e3,
                "peak_rss_mib": peak_mib(), "error": job.record().error,
            }),
        );
    }

    /// Runs one job on the shared engine, as `recon infer` would, into `<job>/out`.
    fn run(&self, job: &Arc<Job>) {
        let t0 = Instant::now();
        if let Some(why) = job.cancel_reason() {
            let (s, e) = why.outcome(self.cfg.job_timeout);
            return self.finish(job, s, Some(e), None, 0.0);
        }
        let started = job.transition(|r| {
            r.status = Status::Running;
            r.started_unix = Some(now_unix());
        });
        if let Err(e) = started {
            let err = JobError { reason: "write".into(), message: format!("storing the job state: {e}") };
            return self.finish(job, Status::Failed, Some(err), None, 0.0);
        }
        log("job", serde_json::json!({"job": job.id, "status": "running"}));
        let deadline = self.cfg.job_timeout.map(|t| t0 + t);
        let outcome = self.compute(job, deadline);
        let seconds = t0.elapsed().as_secs_f64();
        if let Some(why) = job.cancel_reason() {
            let (s, e) = why.outcome(self.cfg.job_timeout);
            return self.finish(job, s, Some(e), None, seconds);
        }
        match outcome {
            Ok((result, written)) => {
                let model = self.engine.pipeline.identity();
                let answer = answer(&job.id, &result, &written, &job.dir.join("out"), seconds, &model);
                for o in &result.objects {
                    for (name, v) in STAGE_COLUMNS.iter().zip(stage_seconds(o)) {
                        self.metrics.stage(name, v);
                    }
                }
                self.metrics.job_seconds(seconds);
                let mut m = self.mean_job_s.lock().unwrap_or_else(PoisonError::into_inner);
                *m = 0.7 * *m + 0.3 * seconds;
                drop(m);
                self.finish(job, Status::Done, None, Some(answer), seconds);
            }
            Err(e) => self.finish(job, Status::Failed, Some(e), None, seconds),
        }
    }

    /// Inputs → engine → output folder; a cancelled job unwinds out of the engine.
    fn compute(&self, job: &Arc<Job>, deadline: Option<Instant>) -> Result<(FrameResult, Vec<WrittenObject>), JobError> {
        let m: Manifest = std::fs::read(job.dir.join("request.json"))
            .ok()
            .and_then(|b| serde_json::from_slice(&b).ok())
            .ok_or_else(|| JobError { reason: "input".into(), message: "the stored request is missing or unreadable".into() })?;
        let loaded = inputs::load(&job.dir, &m, self.engine.pipeline.max_views())
            .map_err(|e| JobError { reason: "input".into(), message: e.message })?;
        let settings = loaded.options.settings().map_err(|e| JobError { reason: "input".into(), message: e.keyword_message() })?;
        let samples = settings.samples.max(1) as f64;
        let state = Mutex::new((0usize, 1usize, 0usize));
        let progress = |p: Progress<'_>| {
            if deadline.is_some_and(|d| Instant::now() > d) {
                job.request_cancel(CancelReason::Timeout);
            }
            if job.cancel_reason().is_some() {
                std::panic::panic_any(Cancelled);
            }
            let mut s = state.lock().unwrap_or_else(PoisonError::into_inner);
            let (stage, frac): (Option<String>, f64) = match p {
                Progress::Object { index, total, label } => {
                    *s = (index, total.max(1), 0);
                    job.update(|r| r.object = Some(format!("{label} [{}/{total}]", index + 1)));
                    (Some("preparing".into()), 0.0)
                }
                Progress::Sample { index, .. } => {
                    s.2 = index;
                    (Some("starting".into()), 0.0)
                }
                Progress::Stage(st) => {
                    let k = [
                        recon_core::engine::Stage::ImageEncoder,
                        recon_core::engine::Stage::SsSampling,
                        recon_core::engine::Stage::SsDecoder,
                        recon_core::engine::Stage::SlatSampling,
                        recon_core::engine::Stage::MeshDecoder,
                        recon_core::engine::Stage::GaussianDecoder,
                    ]
                    .iter()
                    .position(|x| *x == st)
                    .unwrap_or(0);
                    (Some(st.name().to_string()), k as f64 / 6.0)
                }
                Progress::Decimating => (Some("decimating".into()), 0.95),
                Progress::Selecting => (Some("scoring poses".into()), 0.98),
                Progress::ObjectDone { .. } => (None, 1.0),
            };
            let (obj, total, sample) = *s;
            drop(s);
            let done = (obj as f64 + (sample as f64 + frac) / samples) / total as f64;
            job.update(|r| {
                if stage.is_some() {
                    r.stage = stage;
                }
                r.progress = r.progress.max(done.min(1.0));
            });
        };
        let inputs::Loaded { frame, objects, skipped: mask_skips, views, .. } = loaded;
        let others: Vec<SecondView> =
            views.iter().map(|v| SecondView { frame: &v.frame, objects: v.objects.clone(), t_c1_c2: v.t_c1_ci }).collect();
        let run = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            self.engine.reconstruct_views(&frame, objects, others, &settings, &progress)
        }));
        let mut result = match run {
            Ok(Ok(r)) => r,
            Ok(Err(e)) => return Err(JobError { reason: "error".into(), message: e.to_string() }),
            Err(p) if p.is::<Cancelled>() || job.cancel_reason().is_some() => {
                return Err(JobError { reason: "cancelled".into(), message: "cancelled".into() })
            }
            Err(p) => {
                let msg = p.downcast_ref::<String>().cloned().or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()));
                return Err(JobError { reason: "error".into(), message: format!("internal error: {}", msg.unwrap_or_default()) });
            }
        };
        if job.cancel_reason().is_some() {
            return Err(JobError { reason: "cancelled".into(), message: "cancelled".into() });
        }
        // As `recon infer`: the index lists every object that is not there, mask skips first.
        let mut skipped = mask_skips;
        skipped.append(&mut result.skipped);
        result.skipped = skipped;
        job.update(|r| r.stage = Some("writing".into()));
        let written = write_outputs(&result, &job.dir.join("out")).map_err(|e| {
            // Half-written outputs are never served; their space is given back at once.
            let _ = std::fs::remove_dir_all(job.dir.join("out.partial"));
            JobError { reason: "write".into(), message: format!("writing the outputs: {e}") }
        })?;
        Ok((result, written))
    }
}

/// The URL of a file of a job's output folder.
pub fn file_url(id: &str, out: &Path, path: &Path) -> Option<String> {
    let rel = path.strip_prefix(out).ok()?;
    let parts: Vec<String> = rel.components().map(|c| c.as_os_str().to_string_lossy().to_string()).collect();
    Some(format!("/v1/jobs/{id}/files/{}", parts.join("/")))
}

/// `recon infer`'s outputs as the API answers them: one entry per object, reconstructed
/// (`ok`) or not (`skipped`: the mask or its depth; `failed`: the model or post-processing),
/// with the recon and the `model` that answered.
pub fn answer(
    id: &str,
    result: &FrameResult,
    written: &[WrittenObject],
    out: &Path,
    seconds: f64,
    model: &ModelIdentity,
) -> serde_json::Value {
    use recon_core::dataset::SkipReason;
    let url = |p: &Option<PathBuf>| p.as_ref().and_then(|p| file_url(id, out, p));
    let mut objects: Vec<serde_json::Value> = result
        .objects
        .iter()
        .zip(written)
        .map(|(o, w)| {
            let p = &o.pose_camera;
            let (r, t, s) = (p.rotation, p.translation, p.scale);
            let pose: Vec<[f64; 4]> = (0..3)
                .map(|i| [(s * r[i][0]) as f64, (s * r[i][1]) as f64, (s * r[i][2]) as f64, t[i] as f64])
                .chain(std::iter::once([0.0, 0.0, 0.0, 1.0]))
                .collect();
            let q = recon_core::math::matrix_to_quat(&r);
            let stages: serde_json::Map<String, serde_json::Value> =
                STAGE_COLUMNS.iter().zip(stage_seconds(o)).map(|(k, v)| (k.to_string(), serde_json::json!(v))).collect();
            let mut v = serde_json::json!({
                "id": o.id, "label": o.label, "status": "ok",
                "pose": pose, "translation": t, "quaternion_xyzw": [q[1], q[2], q[3], q[0]], "scale": s,
                "score": o.selection.score_m, "stage_seconds": stages, "notes": o.notes,
                // What `recon infer --json` prints of the views: each view of the object, the winner.
                "views": o.views, "selection": o.selection,
                "files": {
                    "pose": file_url(id, out, &w.pose), "mesh_glb": url(&w.mesh_glb), "mesh_ply": url(&w.mesh_ply),
                    "gaussians_ply": url(&w.gaussians_ply),
                },
            });
            // Only when the options asked for it: the answer is otherwise unchanged.
            if let Some(r) = &o.posthoc_color {
                v["posthoc_color"] = serde_json::json!(r);
                v["files"]["posthoc_color"] = serde_json::json!(file_url(id, out, &w.pose.with_file_name("posthoc_color.json")));
            }
            v
        })
        .collect();
    for s in &result.skipped {
        let failed = matches!(s.reason, SkipReason::Preprocessing(_) | SkipReason::Unreadable(_));
        // Another view's mask skips are labelled `view N id 8` (as `recon infer` lists them).
        let label = s
            .label
            .strip_prefix("view ")
            .and_then(|r| r.split_once(' ').filter(|(n, _)| n.parse::<usize>().is_ok()).map(|(_, l)| l))
            .unwrap_or(&s.label);
        let id = label.strip_prefix("id ").and_then(|n| n.parse::<u32>().ok());
        objects.push(serde_json::json!({
            "id": id, "label": s.label, "status": if failed { "failed" } else { "skipped" }, "reason": s.reason.to_string(),
        }));
    }
    let exists = |name: &str| out.join(name).is_file().then(|| format!("/v1/jobs/{id}/files/{name}"));
    serde_json::json!({
        "job": id,
        "objects": objects,
        "files": {
            "index": exists(recon_core::engine::MARKER),
            "scene_glb": exists("scene.glb"),
            "observed_points_ply": exists("observed_points.ply"),
        },
        "archive": format!("/v1/jobs/{id}/archive"),
        "notes": result.notes,
        "seconds": seconds,
        "recon_version": recon_core::VERSION,
        "model_identity": model,
    })
}
