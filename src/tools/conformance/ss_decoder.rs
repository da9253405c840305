//! Runner for the `ss_decoder` fixture (`SparseStructureDecoder`).

use super::fixture::{Check, Fixture};
use crate::model::stage1::ss_vae::decoder::{occupied_coords, SparseStructureDecoder, SparseStructureDecoderConfig};
use crate::model::Compute;
use crate::Result;

pub fn run(fx: &Fixture, compute: Compute) -> Result<Vec<Check>> {
    let cfg = SparseStructureDecoderConfig::from_json(fx.field("args")?, &fx.dir.join("config.json").display().to_string())?;
    let dec = SparseStructureDecoder::new(&cfg, fx.var_builder(), compute)?;
    let tol = fx.abs_tolerance(1e-4);
    let trace = dec.forward_traced(fx.tensor("input.x")?)?;
    let mut checks = vec![
        fx.check("output.logits", &trace.logits, tol)?,
        fx.check("intermediate.input_layer", &trace.input_layer, tol)?,
        fx.check("intermediate.middle_block", &trace.middle_block, tol)?,
    ];
    // Occupancy is what the pipeline consumes: compare the count exactly, and
    // the voxel sets against the fixture's own logits.
    let got = occupied_coords(&trace.logits)?;
    if let Some(want) = fx.config.get("occupancy").and_then(|o| o.get("num_occupied")).and_then(|v| v.as_u64()) {
        checks.push(
            Check::exact("occupancy.num_occupied", (got.len() as i64 - want as i64).unsigned_abs() as usize)
                .with_note(format!("got {} want {want}", got.len())),
        );
    }
    let want_coords = occupied_coords(fx.tensor("output.logits")?)?;
    let mismatch = if got == want_coords {
        0
    } else {
        let a: std::collections::HashSet<_> = got.iter().collect();
        let b: std::collections::HashSet<_> = want_coords.iter().collect();
        a.symmetric_difference(&b).count().max(1)
    };
    checks.push(Check::exact("occupancy.coords", mismatch).with_note("vs argwhere(output.logits > 0)"));
    Ok(checks)
}
