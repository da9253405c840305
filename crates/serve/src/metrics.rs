//! Counters and histograms for `GET /metrics` (Prometheus text format 0.0.4).

use std::collections::BTreeMap;
use std::fmt::Write;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, PoisonError};

/// Upper bounds of the seconds histograms.
const BUCKETS: [f64; 14] = [0.01, 0.05, 0.1, 0.25, 0.5, 1.0, 2.0, 5.0, 10.0, 30.0, 60.0, 120.0, 300.0, 600.0];

#[derive(Default, Clone)]
struct Histogram {
    counts: [u64; BUCKETS.len()],
    count: u64,
    sum: f64,
}

impl Histogram {
    fn observe(&mut self, v: f64) {
        for (c, b) in self.counts.iter_mut().zip(BUCKETS) {
            if v <= b {
                *c += 1;
            }
        }
        self.count += 1;
        self.sum += v;
    }

    fn write(&self, out: &mut String, name: &str, labels: &str) {
        let sep = if labels.is_empty() { "" } else { "," };
        for (c, b) in self.counts.iter().zip(BUCKETS) {
            let _ = writeln!(out, "{name}_bucket{{{labels}{sep}le=\"{b}\"}} {c}");
        }
        let _ = writeln!(out, "{name}_bucket{{{labels}{sep}le=\"+Inf\"}} {}", self.count);
        let braces = if labels.is_empty() { String::new() } else { format!("{{{labels}}}") };
        let _ = writeln!(out, "{name}_sum{braces} {}", self.sum);
        let _ = writeln!(out, "{name}_count{braces} {}", self.count);
    }
}

/// The server's counters.
#[derive(Default)]
pub struct Metrics {
    accepted: AtomicU64,
    rejected_full: AtomicU64,
    done: AtomicU64,
    failed: AtomicU64,
    cancelled: AtomicU64,
    requests: Mutex<BTreeMap<u16, u64>>,
    stages: Mutex<BTreeMap<String, Histogram>>,
    jobs: Mutex<Histogram>,
}

impl Metrics {
    /// A job was queued.
    pub fn accepted(&self) {
        self.accepted.fetch_add(1, Ordering::Relaxed);
    }

    /// A request was refused for a full queue.
    pub fn rejected_full(&self) {
        self.rejected_full.fetch_add(1, Ordering::Relaxed);
    }

    /// A job ended with `status` (`done`, `failed` or `cancelled`).
    pub fn finished(&self, status: &str) {
        let c = match status {
            "done" => &self.done,
            "failed" => &self.failed,
            "cancelled" => &self.cancelled,
            _ => return,
        };
        c.fetch_add(1, Ordering::Relaxed);
    }

    /// A request was answered with `status`.
    pub fn request(&self, status: u16) {
        *self.requests.lock().unwrap_or_else(PoisonError::into_inner).entry(status).or_default() += 1;
    }

    /// One object's seconds in one stage (`recon infer`'s stage columns).
    pub fn stage(&self, name: &str, seconds: f64) {
        self.stages.lock().unwrap_or_else(PoisonError::into_inner).entry(name.to_string()).or_default().observe(seconds);
    }

    /// A job's seconds, queue wait excluded.
    pub fn job_seconds(&self, seconds: f64) {
        self.jobs.lock().unwrap_or_else(PoisonError::into_inner).observe(seconds);
    }

    /// The Prometheus text, with the gauges read now.
    pub fn render(&self, queued: usize, running: usize, ready: bool) -> String {
        let mut s = String::new();
        let gauge = |s: &mut String, name: &str, help: &str, v: String| {
            let _ = writeln!(s, "# HELP {name} {help}\n# TYPE {name} gauge\n{name} {v}");
        };
        gauge(&mut s, "recon_queue_depth", "Jobs waiting for a worker (uploads holding a place included).", queued.to_string());
        gauge(&mut s, "recon_jobs_running", "Jobs being computed.", running.to_string());
        gauge(&mut s, "recon_ready", "1 when the model is loaded and the queue has room.", u8::from(ready).to_string());
        let peak = recon_core::util::peak_rss_mib().map_or(0.0, |m| m * 1048576.0);
        gauge(&mut s, "recon_peak_resident_memory_bytes", "Peak resident memory of the process (VmHWM).", format!("{peak}"));
        gauge(
            &mut s,
            "recon_resident_memory_bytes",
            "Resident memory of the process now (VmRSS).",
            crate::log::rss_bytes().unwrap_or(0).to_string(),
        );
        let _ = writeln!(s, "# HELP recon_jobs_total Jobs by final status (accepted: queued).\n# TYPE recon_jobs_total counter");
        for (k, c) in [("accepted", &self.accepted), ("done", &self.done), ("failed", &self.failed), ("cancelled", &self.cancelled)] {
            let _ = writeln!(s, "recon_jobs_total{{status=\"{k}\"}} {}", c.load(Ordering::Relaxed));
        }
        let _ = writeln!(
            s,
            "# HELP recon_rejected_queue_full_total Requests answered 429 for a full queue.\n# TYPE recon_rejected_queue_full_total counter\nrecon_rejected_queue_full_total {}",
            self.rejected_full.load(Ordering::Relaxed)
        );
        let _ = writeln!(s, "# HELP recon_http_requests_total Requests by HTTP status.\n# TYPE recon_http_requests_total counter");
        for (code, n) in self.requests.lock().unwrap_or_else(PoisonError::into_inner).iter() {
            let _ = writeln!(s, "recon_http_requests_total{{code=\"{code}\"}} {n}");
        }
        let _ = writeln!(
            s,
            "# HELP recon_stage_seconds Seconds per object and stage (recon infer's stage columns).\n# TYPE recon_stage_seconds histogram"
        );
        for (name, h) in self.stages.lock().unwrap_or_else(PoisonError::into_inner).iter() {
            h.write(&mut s, "recon_stage_seconds", &format!("stage=\"{name}\""));
        }
        let _ = writeln!(s, "# HELP recon_job_seconds Seconds per job, queue wait excluded.\n# TYPE recon_job_seconds histogram");
        self.jobs.lock().unwrap_or_else(PoisonError::into_inner).write(&mut s, "recon_job_seconds", "");
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn text_format() {
        let m = Metrics::default();
        m.accepted();
        m.finished("done");
        m.stage("total", 0.3);
        m.request(200);
        let t = m.render(2, 1, true);
        assert!(t.contains("recon_queue_depth 2\n"), "{t}");
        assert!(t.contains("recon_jobs_total{status=\"done\"} 1"), "{t}");
        assert!(t.contains("recon_stage_seconds_bucket{stage=\"total\",le=\"0.5\"} 1"), "{t}");
        assert!(t.contains("recon_stage_seconds_bucket{stage=\"total\",le=\"0.25\"} 0"), "{t}");
        assert!(t.contains("recon_job_seconds_count 0"), "{t}");
        assert!(t.contains("recon_http_requests_total{code=\"200\"} 1"), "{t}");
    }
}
