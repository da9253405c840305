//! `dinov2_reg_cond`: DINOv2 ViT with registers under torch.hub names
//! (`hub.` prefix in the fixture), plus the TRELLIS conditioning and the
//! image normalisation constants.

use super::fixture::{Check, Fixture};
use crate::dataset::image::normalize_01;
use crate::model::stage1::dinov2::{trellis_cond, Dinov2, Dinov2Config};
use crate::model::Compute;
use crate::Result;

pub fn run(fx: &Fixture, compute: Compute) -> Result<Vec<Check>> {
    let file = fx.dir.join("config.json").display().to_string();
    let cfg = Dinov2Config::from_json(fx.field("hf_config")?, &file)?;
    let model = Dinov2::new(&cfg, fx.var_builder().pp("hub"), compute)?;
    let tol = fx.abs_tolerance(1e-4);

    let pixels = fx.tensor("input.pixel_values")?;
    let out = model.forward(pixels)?;
    let cond = trellis_cond(&out.x_prenorm)?;
    let pooler = out.last_hidden_state.narrow(1, 0, 1)?.squeeze(1)?;

    let mut checks = vec![
        fx.check("output.embeddings", &out.embeddings, tol)?,
        fx.check("output.x_prenorm", &out.x_prenorm, tol)?,
        fx.check("output.last_hidden_state", &out.last_hidden_state, tol)?,
        fx.check("output.pooler_output", &pooler, tol)?,
        fx.check("output.cond", &cond, tol)?,
    ];
    // Our normalisation constants reproduce the fixture's pixel values.
    let norm = normalize_01(fx.tensor("input.image_01")?)?;
    checks.push(fx.check("input.pixel_values", &norm, 1e-5)?.with_note("normalize(image_01)"));
    Ok(checks)
}
