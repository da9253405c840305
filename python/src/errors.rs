//! recon's typed errors as Python exceptions: `ReconError` and its subclasses
//! `InputError` (files, arrays, masks, datasets), `WeightsError` (loading a model) and
//! `ConfigError` (an option or a configuration field out of range). The message is the
//! library's, as the CLI prints it.

use pyo3::create_exception;
use pyo3::exceptions::PyException;
use pyo3::PyErr;

create_exception!(recon_rgbd, ReconError, PyException, "Base class of every error recon raises.");
create_exception!(recon_rgbd, InputError, ReconError, "Bad input: a file, an array, a mask or a dataset is not what recon expects.");
create_exception!(recon_rgbd, WeightsError, ReconError, "The model's weights could not be found, read or matched to the architecture.");
create_exception!(recon_rgbd, ConfigError, ReconError, "An option or a configuration field is missing or out of range.");
create_exception!(
    recon_rgbd,
    DefaultModelWarning,
    pyo3::exceptions::PyUserWarning,
    "The embedded recgen-nano answers because no weights were given (warned once per process)."
);

/// A library error, classified by its kind.
pub fn to_py(e: recon::Error) -> PyErr {
    use recon::Error as E;
    let msg = e.to_string();
    match e {
        E::Io { .. } | E::Json { .. } | E::Input { .. } | E::TooLarge(_) => InputError::new_err(msg),
        E::Config { .. } => ConfigError::new_err(msg),
        E::MissingTensor { .. } | E::ShapeMismatch { .. } | E::UnexpectedTensors { .. } | E::ChecksumMismatch { .. } => {
            WeightsError::new_err(msg)
        }
        _ => ReconError::new_err(msg),
    }
}

/// An error while loading a model: files and inputs there are the weights.
pub fn weights_to_py(e: recon::Error) -> PyErr {
    use recon::Error as E;
    match e {
        // (Msg: a failed download, or a release file that does not parse.)
        E::Io { .. } | E::Json { .. } | E::Input { .. } | E::Msg(_) => WeightsError::new_err(e.to_string()),
        other => to_py(other),
    }
}

/// A bad argument of a Python call, named like the CLI flag it mirrors.
pub fn config(field: &str, msg: impl std::fmt::Display) -> PyErr {
    ConfigError::new_err(format!("{field}: {msg}"))
}

pub fn input(what: &str, msg: impl std::fmt::Display) -> PyErr {
    InputError::new_err(format!("{what}: {msg}"))
}

/// `.map_err(py_err)` on library results.
pub trait IntoPy<T> {
    fn py(self) -> pyo3::PyResult<T>;
}

impl<T> IntoPy<T> for recon::Result<T> {
    fn py(self) -> pyo3::PyResult<T> {
        self.map_err(to_py)
    }
}
