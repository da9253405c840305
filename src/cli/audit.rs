//! `recon audit`: find what a simulation gets wrong (depth sensor or any table).
use anyhow::Context;
use recon::audit::ResidualTable;
use recon::audit::SearchOptions;
use recon::audit::{audit_depth, audit_depth_frames, audit_table, write_outputs, Audit, MechanismOptions};
use recon::audit::{collect, residual_table, DepthOptions};
use recon::sensor::SensorModel;
use std::path::{Path, PathBuf};

#[derive(clap::Subcommand)]
pub enum AuditCmd {
    /// Measured vs simulated depth of a BOP / YCB-Video dataset: findings, extended sensor model, gain.
    Depth(DepthArgs),
    /// The same search on any CSV table of measured vs simulated values (other columns are covariates).
    Table(TableArgs),
}

#[derive(clap::Args)]
pub struct SearchArgs {
    /// Family-wise significance level of each selection round (randomisation test over its candidates).
    #[arg(long, default_value_t = SearchOptions::default().alpha)]
    alpha: f64,
    /// At most this many findings.
    #[arg(long, default_value_t = SearchOptions::default().max_findings)]
    max_findings: usize,
    /// Plain Gaussian residuals (no outlier component).
    #[arg(long)]
    no_robust: bool,
    /// Skip the final interaction round.
    #[arg(long)]
    no_interactions: bool,
    /// Leave-one-unit-out up to this many units, K-fold beyond.
    #[arg(long, default_value_t = SearchOptions::default().max_folds)]
    max_folds: usize,
    /// Seed of the pixel subsample and of the fold assignment.
    #[arg(long, default_value_t = SearchOptions::default().seed)]
    seed: u64,
    /// Output folder (report.json, summary.txt, report.html, plots/; for depth maps/ and sensor_extended.json).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Also write the report JSON here.
    #[arg(long)]
    json: Option<PathBuf>,
}

impl SearchArgs {
    fn options(&self) -> anyhow::Result<SearchOptions> {
        let o = SearchOptions {
            alpha: self.alpha,
            max_findings: self.max_findings,
            robust: !self.no_robust,
            interactions: !self.no_interactions,
            max_folds: self.max_folds,
            seed: self.seed,
            ..Default::default()
        };
        o.validate()?;
        Ok(o)
    }
}

#[derive(clap::Args)]
pub struct DepthArgs {
    /// Dataset: a BOP dataset root or split (e.g. `recon synth` output), or the YCB-Video layout.
    #[arg(long)]
    dataset: PathBuf,
    /// Sensor model JSON to audit (default: ideal — exact depth, no dropout).
    #[arg(long)]
    sensor: Option<PathBuf>,
    /// Object pixels compared per frame (seeded random subset).
    #[arg(long, default_value_t = DepthOptions::default().max_pixels_per_frame)]
    max_pixels: usize,
    /// Use only the first N frames.
    #[arg(long)]
    frames: Option<usize>,
    /// Skip the mechanism inference (which fits registration, distortion, drift, edge
    /// effects, … to the frame images and names the winning physical mechanism).
    #[arg(long)]
    no_mechanisms: bool,
    #[command(flatten)]
    search: SearchArgs,
}

#[derive(clap::Args)]
pub struct TableArgs {
    /// CSV file with a header row.
    #[arg(long)]
    data: PathBuf,
    /// Column of measured values (empty / NA = missing measurement).
    #[arg(long)]
    measured: String,
    /// Column of simulated values.
    #[arg(long)]
    simulated: String,
    /// Column grouping rows into split units (default: `frame` if present, else each row).
    #[arg(long)]
    unit: Option<String>,
    /// Columns to treat as categorical (text columns always are).
    #[arg(long, value_delimiter = ',')]
    categorical: Vec<String>,
    /// Columns that are not covariates (ids, notes).
    #[arg(long, value_delimiter = ',')]
    ignore: Vec<String>,
    #[command(flatten)]
    search: SearchArgs,
}

pub fn run(cmd: AuditCmd) -> anyhow::Result<bool> {
    match cmd {
        AuditCmd::Depth(a) => depth(a),
        AuditCmd::Table(a) => table(a),
    }
}

fn default_out(input: &Path) -> PathBuf {
    let name = input.file_name().map(|s| s.to_string_lossy().to_string()).unwrap_or_else(|| "data".into());
    PathBuf::from(format!("audit-{name}"))
}

fn finish(mut audit: Audit, args: &SearchArgs, input: &Path) -> anyhow::Result<bool> {
    let out = args.out.clone().unwrap_or_else(|| default_out(input));
    let files = write_outputs(&mut audit, &out, args.json.as_deref())?;
    print!("{}", audit.report.summary());
    println!(
        "wrote {} files under {}{}",
        files.len(),
        out.display(),
        args.json.as_ref().map(|j| format!(" and {}", j.display())).unwrap_or_default()
    );
    Ok(true)
}

fn depth(a: DepthArgs) -> anyhow::Result<bool> {
    let opts = a.search.options()?;
    let model = match &a.sensor {
        Some(p) => SensorModel::load(p)?,
        None => SensorModel::ideal(),
    };
    if a.max_pixels == 0 {
        anyhow::bail!("--max-pixels must be ≥ 1");
    }
    let dopts = DepthOptions { max_pixels_per_frame: a.max_pixels, seed: a.search.seed, max_frames: a.frames };
    let t0 = std::time::Instant::now();
    let col = collect(&a.dataset, &model, &dopts).with_context(|| format!("reading and simulating {}", a.dataset.display()))?;
    eprintln!(
        "{} frames, {} object pixels, {} compared ({}); {:.1} s",
        col.frames,
        col.object_pixels,
        col.pixels.len(),
        col.simulation,
        t0.elapsed().as_secs_f64()
    );
    let mut table = residual_table(&model, &col.pixels, &a.dataset.display().to_string());
    // Units are frame indices; show them as scene/frame.
    table.unit_names = table
        .unit_names
        .iter()
        .map(|s| s.parse::<usize>().ok().and_then(|i| col.frame_names.get(i).cloned()).unwrap_or_else(|| s.clone()))
        .collect();
    let t1 = std::time::Instant::now();
    let audit = if a.no_mechanisms {
        audit_depth(&table, &opts, &model)?
    } else {
        audit_depth_frames(&table, &opts, &model, &col.sims, &MechanismOptions::from_search(&opts))?
    };
    eprintln!("search: {:.1} s", t1.elapsed().as_secs_f64());
    finish(audit, &a.search, &a.dataset)
}

fn table(a: TableArgs) -> anyhow::Result<bool> {
    let opts = a.search.options()?;
    let (table, skipped) = ResidualTable::from_csv(&a.data, &a.measured, &a.simulated, a.unit.as_deref(), &a.categorical, &a.ignore)?;
    if skipped > 0 {
        eprintln!("note: {skipped} row(s) without a simulated value or a covariate were skipped");
    }
    let audit = audit_table(&table, &opts)?;
    finish(audit, &a.search, &a.data)
}
