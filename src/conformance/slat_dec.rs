use super::{Check, Fixture};
use crate::{Error, Result};

pub fn run_gs(fx: &Fixture) -> Result<Vec<Check>> {
    Err(Error::msg(format!("{}: runner for `{}` not built yet", fx.name(), fx.module())))
}

pub fn run_mesh(fx: &Fixture) -> Result<Vec<Check>> {
    Err(Error::msg(format!("{}: runner for `{}` not built yet", fx.name(), fx.module())))
}
