use super::{Check, Fixture};
use crate::{Error, Result};

pub fn run(fx: &Fixture) -> Result<Vec<Check>> {
    Err(Error::msg(format!("{}: runner for `{}` not built yet", fx.name(), fx.module())))
}
