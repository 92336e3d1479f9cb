//! `svkernel._svkernel`: the native half of the Python package.
//!
//! Each function takes arrays that the Python half (`svkernel/__init__.py`)
//! has already broadcast, made contiguous float64 and checked for shape, and
//! calls the library; heavy work runs with the GIL released. Library errors
//! become the exceptions of `svkernel._errors`, with the library's message
//! (which names the file and the key).
use numpy::{IntoPyArray, PyArray1, PyArrayMethods, PyReadonlyArray1};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};
use svkernel::design::{self, Settings};
use svkernel::forward::runner::chunk_range;
use svkernel::forward::tally::RadialBins;
use svkernel::jobs::render::{RenderOptions, Target, metrics, render_scene};
use svkernel::prelude::*;
use svkernel::provenance::Provenance;
use svkernel::render::estimator::Allocation;

/// A library error as the matching exception of `svkernel._errors`.
fn py_err(e: svkernel::Error) -> PyErr {
    Python::attach(|py| {
        let (class, key, path) = match &e {
            Error::Param { name, .. } => ("InvalidParameter", Some(name.to_string()), None),
            Error::Format { path, key, .. } => ("FormatError", Some(key.clone()), Some(path)),
            Error::Io { path, .. } => ("FileError", None, Some(path)),
            Error::Merge { path, .. } => ("FormatError", None, Some(path)),
            _ => ("FitError", None, None),
        };
        let made = (|| -> PyResult<PyErr> {
            let module = py.import("svkernel._errors")?;
            let exc = module.getattr(class)?.call1((
                e.to_string(),
                key,
                path.map(|p| p.display().to_string()),
            ))?;
            Ok(PyErr::from_value(exc))
        })();
        made.unwrap_or_else(|err| err)
    })
}

fn lib<T>(r: svkernel::Result<T>) -> PyResult<T> {
    r.map_err(py_err)
}

/// The models: from the environment variables or the built-in copies,
/// loaded once per process; `meta` replaces the meta-model.
fn models(meta: Option<&MetaModel>) -> PyResult<Models> {
    static FOUND: OnceLock<Models> = OnceLock::new();
    let base = match FOUND.get() {
        Some(m) => m.clone(),
        None => {
            let m = lib(Models::find([None; 4], None))?;
            FOUND.get_or_init(|| m).clone()
        }
    };
    Ok(match meta {
        Some(m) => Models {
            meta: m.inner.clone(),
            meta_origin: PathBuf::from(&m.origin),
            ..base
        },
        None => base,
    })
}

/// A kernel meta-model: the built-in one, one read from a file, or one
/// fitted by `fit_kernels`.
#[pyclass(module = "svkernel._svkernel", frozen)]
struct MetaModel {
    inner: Arc<MetaModelFile>,
    origin: String,
}

#[pymethods]
impl MetaModel {
    /// The meta-model in use by default: the file named by `SVKERNEL_MODEL`
    /// if set, else the built-in one.
    #[staticmethod]
    fn default() -> PyResult<Self> {
        let m = models(None)?;
        Ok(MetaModel {
            inner: m.meta,
            origin: m.meta_origin.display().to_string(),
        })
    }

    /// Reads a meta-model file (`svkernel fit-kernels` writes them).
    #[staticmethod]
    fn load(path: PathBuf) -> PyResult<Self> {
        Ok(MetaModel {
            inner: Arc::new(lib(MetaModelFile::load(&path))?),
            origin: path.display().to_string(),
        })
    }

    /// Parses a meta-model document from its JSON text.
    #[staticmethod]
    #[pyo3(signature = (text, origin = "<json>".to_string()))]
    fn from_json(text: &str, origin: String) -> PyResult<Self> {
        Ok(MetaModel {
            inner: Arc::new(lib(svkernel::doc::from_json(text, Path::new(&origin)))?),
            origin,
        })
    }

    /// The document as JSON text.
    fn to_json(&self) -> PyResult<String> {
        to_json(&*self.inner)
    }

    /// Writes the document to `path` (atomically: never a partial file).
    fn save(&self, path: PathBuf) -> PyResult<()> {
        lib(svkernel::jobs::store::write_json_atomic(
            &path,
            &*self.inner,
        ))
    }

    /// Where the model came from (a path, or `<json>` / `<fit>`).
    #[getter]
    fn origin(&self) -> &str {
        &self.origin
    }

    /// Components K of the all-vertex kernel.
    #[getter]
    fn components(&self) -> usize {
        self.inner.all.k
    }

    fn __repr__(&self) -> String {
        format!(
            "MetaModel(origin={:?}, components={})",
            self.origin, self.inner.all.k
        )
    }
}

/// A float64 numpy vector.
type Floats<'py> = Bound<'py, PyArray1<f64>>;

fn slice<'a>(a: &'a PyReadonlyArray1<'_, f64>, name: &str) -> PyResult<&'a [f64]> {
    a.as_slice()
        .map_err(|_| PyValueError::new_err(format!("{name}: a contiguous float64 array")))
}

/// Kernels at (d, α, ρ) triples: (weights (N, K), centres (N, K, 2),
/// widths (N, K), clamped (N,)). Mixtures with fewer components are padded
/// with zero weights.
#[pyfunction]
#[pyo3(signature = (d, albedo, density, vertices, manual, meta=None))]
#[allow(clippy::type_complexity)]
fn kernel<'py>(
    py: Python<'py>,
    d: PyReadonlyArray1<'py, f64>,
    albedo: PyReadonlyArray1<'py, f64>,
    density: PyReadonlyArray1<'py, f64>,
    vertices: &str,
    manual: bool,
    meta: Option<PyRef<'py, MetaModel>>,
) -> PyResult<(
    Bound<'py, PyAny>,
    Bound<'py, PyAny>,
    Bound<'py, PyAny>,
    Bound<'py, PyArray1<bool>>,
)> {
    let class = lib(VertexClass::parse(vertices))?;
    let models = models(meta.as_deref())?;
    let (d, a, r) = (
        slice(&d, "d")?,
        slice(&albedo, "albedo")?,
        slice(&density, "density")?,
    );
    let n = d.len();
    let (gmms, clamped): (Vec<Gmm>, Vec<bool>) = py.detach(|| {
        (0..n)
            .map(|i| {
                if manual {
                    let unit =
                        manual_kernel(svkernel::metamodel::kernel::optical_distance(d[i], r[i]));
                    (
                        svkernel::metamodel::kernel::scale_for_density(&unit, r[i]),
                        false,
                    )
                } else {
                    let q = models.meta.eval(class, d[i], a[i], r[i]);
                    (q.gmm, q.clamped)
                }
            })
            .unzip()
    });
    let k = gmms.iter().map(|g| g.components.len()).max().unwrap_or(0);
    let mut w = vec![0.0; n * k];
    let mut c = vec![0.0; n * k * 2];
    let mut s = vec![0.0; n * k];
    for (i, g) in gmms.iter().enumerate() {
        for (j, comp) in g.components.iter().enumerate() {
            w[i * k + j] = comp.weight;
            c[(i * k + j) * 2] = comp.t;
            c[(i * k + j) * 2 + 1] = comp.s;
            s[i * k + j] = comp.sigma;
        }
    }
    Ok((
        w.into_pyarray(py).reshape([n, k])?.into_any(),
        c.into_pyarray(py).reshape([n, k, 2])?.into_any(),
        s.into_pyarray(py).reshape([n, k])?.into_any(),
        clamped.into_pyarray(py),
    ))
}

/// The basis BSSRDF's homogeneous profile at each albedo and radius.
#[pyfunction]
#[pyo3(signature = (albedo, radii, incidence))]
fn profile<'py>(
    py: Python<'py>,
    albedo: PyReadonlyArray1<'py, f64>,
    radii: PyReadonlyArray1<'py, f64>,
    incidence: &str,
) -> PyResult<Bound<'py, PyDict>> {
    let models = models(None)?;
    let basis = match incidence {
        "collimated" => models.basis.clone(),
        "diffuse" => models.basis_diffuse.clone(),
        other => {
            return Err(py_err(Error::Param {
                name: "incidence",
                value: other.to_string(),
                allowed: "collimated or diffuse",
            }));
        }
    };
    let (a, r) = (slice(&albedo, "albedo")?, slice(&radii, "radii")?);
    let (n, m) = (a.len(), r.len());
    let mut out: [Vec<f64>; 3] = Default::default();
    let mut totals: [Vec<f64>; 3] = Default::default();
    py.detach(|| {
        for &alpha in a {
            let (r1, rm) = basis.r_1_m(alpha);
            totals[0].push(basis.r_d(alpha));
            totals[1].push(r1);
            totals[2].push(rm);
            for &ri in r {
                out[0].push(basis.exitance(ri, alpha));
                out[1].push(basis.density(ri, alpha));
                out[2].push(basis.cdf(ri, alpha));
            }
        }
    });
    let dict = PyDict::new(py);
    for (name, v) in ["R_d", "R_1", "R_m"].into_iter().zip(totals) {
        dict.set_item(name, v.into_pyarray(py))?;
    }
    for (name, v) in ["exitance", "density", "cdf"].into_iter().zip(out) {
        dict.set_item(name, v.into_pyarray(py).reshape([n, m])?)?;
    }
    Ok(dict)
}

/// An SV-BSSRDF over texel maps (module `svkernel.SvBssrdf` documents it).
#[pyclass(name = "_SvBssrdf", module = "svkernel._svkernel", frozen)]
struct PySvBssrdf {
    inner: Arc<SvBssrdf>,
}

#[pymethods]
impl PySvBssrdf {
    /// `albedo`: (C, ny, nx) flattened; `density`: None, a constant, or
    /// (ny, nx) flattened.
    #[new]
    #[pyo3(signature = (albedo, channels, ny, nx, texel, method, incidence, density_constant, density_map=None, meta=None))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        py: Python<'_>,
        albedo: PyReadonlyArray1<'_, f64>,
        channels: usize,
        ny: usize,
        nx: usize,
        texel: f64,
        method: &str,
        incidence: &str,
        density_constant: f64,
        density_map: Option<PyReadonlyArray1<'_, f64>>,
        meta: Option<PyRef<'_, MetaModel>>,
    ) -> PyResult<Self> {
        let method = lib(Method::parse(method))?;
        let models = models(meta.as_deref())?;
        let basis = match incidence {
            "collimated" => models.basis.clone(),
            "diffuse" => models.basis_diffuse.clone(),
            other => {
                return Err(py_err(Error::Param {
                    name: "incidence",
                    value: other.to_string(),
                    allowed: "collimated or diffuse",
                }));
            }
        };
        let values = slice(&albedo, "albedo")?;
        let maps = lib((0..channels)
            .map(|c| {
                TexelMap::new(
                    nx,
                    ny,
                    texel,
                    values[c * nx * ny..(c + 1) * nx * ny].to_vec(),
                )
            })
            .collect::<svkernel::Result<Vec<_>>>())?;
        let density = match &density_map {
            Some(m) => Density::Map(lib(TexelMap::new(
                nx,
                ny,
                texel,
                slice(m, "density")?.to_vec(),
            ))?),
            None => Density::Constant(density_constant),
        };
        let inner = py.detach(|| {
            SvBssrdf::new(
                method,
                Variant::default(),
                Arc::new(BasisTable::new(&basis)),
                Some(models.meta.clone()),
                maps,
                density,
            )
        });
        Ok(PySvBssrdf {
            inner: Arc::new(lib(inner)?),
        })
    }

    #[getter]
    fn channels(&self) -> usize {
        self.inner.channels()
    }

    /// S(x_i, x_e) per pair and channel: (N·C) values, pair-major.
    fn eval<'py>(
        &self,
        py: Python<'py>,
        xi: PyReadonlyArray1<'py, f64>,
        xe: PyReadonlyArray1<'py, f64>,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        let (xi, xe) = (slice(&xi, "xi")?, slice(&xe, "xe")?);
        let s = &self.inner;
        let channels = s.channels();
        let out = py.detach(|| {
            let mut scratch = Scratch::default();
            let mut out = Vec::with_capacity(xi.len() / 2 * channels);
            for (i, e) in xi.chunks_exact(2).zip(xe.chunks_exact(2)) {
                for c in 0..channels {
                    out.push(s.eval(c, [i[0], i[1]], [e[0], e[1]], &mut scratch));
                }
            }
            out
        });
        Ok(out.into_pyarray(py))
    }

    /// Importance-sampled entry points for exit points `xe` from uniform
    /// numbers `u`: (x_i flattened (N·2), pdf (N)).
    fn sample<'py>(
        &self,
        py: Python<'py>,
        xe: PyReadonlyArray1<'py, f64>,
        u: PyReadonlyArray1<'py, f64>,
    ) -> PyResult<(Floats<'py>, Floats<'py>)> {
        let (xe, u) = (slice(&xe, "xe")?, slice(&u, "u")?);
        let s = &self.inner;
        let (xi, pdf) = py.detach(|| {
            let mut xi = Vec::with_capacity(xe.len());
            let mut pdf = Vec::with_capacity(xe.len() / 2);
            for (e, u) in xe.chunks_exact(2).zip(u.chunks_exact(2)) {
                let sample = s.sample_entry([e[0], e[1]], [u[0], u[1]]);
                xi.extend(sample.xi);
                pdf.push(sample.pdf);
            }
            (xi, pdf)
        });
        Ok((xi.into_pyarray(py), pdf.into_pyarray(py)))
    }
}

/// Renders a scene and returns its passes: the scene is `text` (TOML,
/// named `origin` in errors, texture files relative to its folder), or if
/// `text` is None the file or canonical scene `origin`.
#[pyfunction]
#[pyo3(signature = (text, origin, methods, spp, reference_paths, seed, progress, meta=None, allocation=None))]
#[allow(clippy::too_many_arguments)]
fn render<'py>(
    py: Python<'py>,
    text: Option<&str>,
    origin: PathBuf,
    methods: Option<Vec<String>>,
    spp: Option<u32>,
    reference_paths: Option<u64>,
    seed: u64,
    progress: bool,
    meta: Option<PyRef<'py, MetaModel>>,
    allocation: Option<&str>,
) -> PyResult<Bound<'py, PyList>> {
    let scene = lib(match text {
        Some(text) => Scene::from_toml(text, &origin),
        None => Scene::find(&origin),
    })?;
    let out = tempfile::tempdir().map_err(|e| {
        py_err(Error::Io {
            path: std::env::temp_dir(),
            source: e,
        })
    })?;
    let mut opts = RenderOptions::new(out.path().to_path_buf(), models(meta.as_deref())?);
    if let Some(methods) = methods {
        opts.targets = methods
            .iter()
            .map(|m| lib(Target::parse(m)))
            .collect::<PyResult<_>>()?;
    }
    opts.spp = spp;
    if let Some(a) = allocation {
        opts.allocation = lib(Allocation::parse(a))?;
    }
    opts.reference_paths = reference_paths;
    opts.seed = seed;
    opts.run.progress = progress;
    let passes = py.detach(|| render_scene(&scene, &opts));
    let passes = lib(passes)?;
    let list = PyList::empty(py);
    for pass in &passes {
        let reference = pass
            .rendered
            .iter()
            .find(|r| matches!(r.target, Target::Reference));
        let methods = PyDict::new(py);
        for r in &pass.rendered {
            let img = &r.image;
            let (n, c) = (img.resolution, img.channels);
            // The library stores channel-major planes; Python gets (n, n, C).
            let planar = |v: &[f64]| -> Vec<f64> {
                let mut out = vec![0.0; v.len()];
                for ch in 0..c {
                    for p in 0..n * n {
                        out[p * c + ch] = v[ch * n * n + p];
                    }
                }
                out
            };
            let entry = PyDict::new(py);
            entry.set_item(
                "mean",
                planar(&img.mean).into_pyarray(py).reshape([n, n, c])?,
            )?;
            entry.set_item(
                "stderr",
                planar(&img.stderr).into_pyarray(py).reshape([n, n, c])?,
            )?;
            entry.set_item("seconds", r.wall_s)?;
            if let (Some(reference), Target::Model(_)) = (reference, r.target) {
                let m = metrics(img, &reference.image);
                entry.set_item("rel_rmse", m.rel_rmse)?;
                entry.set_item("rel_bias", m.rel_bias)?;
                entry.set_item("resolution", m.resolution)?;
                entry.set_item(
                    "channels",
                    m.channels
                        .iter()
                        .map(|c| (c.rel_rmse, c.rel_bias))
                        .collect::<Vec<_>>(),
                )?;
            }
            methods.set_item(r.target.name(), entry)?;
        }
        let p = PyDict::new(py);
        p.set_item("tag", &pass.tag)?;
        p.set_item("density", pass.density)?;
        p.set_item("methods", methods)?;
        list.append(p)?;
    }
    Ok(list)
}

/// A simulated homogeneous profile (`svkernel simulate-profile`), as the
/// JSON text of its document.
#[pyfunction]
#[pyo3(signature = (albedo, g, eta, density, source, paths, seed, max_events, thickness, progress))]
#[allow(clippy::too_many_arguments)]
fn simulate_profile(
    py: Python<'_>,
    albedo: f64,
    g: f64,
    eta: f64,
    density: f64,
    source: &str,
    paths: u64,
    seed: u64,
    max_events: u32,
    thickness: Option<f64>,
    progress: bool,
) -> PyResult<String> {
    let medium = lib(Medium::new(albedo, g, eta, density, thickness))?;
    let source = lib(Source::parse(source))?;
    let config = ProfileConfig {
        medium,
        source,
        paths,
        seed,
        max_events,
        bins: RadialBins::default(),
        engine: Engine::Lanes,
        radiance: false,
    };
    lib(config.validate())?;
    let opts = RunOptions {
        progress,
        ..Default::default()
    };
    let doc = py.detach(|| -> svkernel::Result<ProfileDoc> {
        let (tally, wall_s) = config.run(None, &opts)?;
        let chunks = vec![chunk_range(config.paths, None)];
        Ok(ProfileDoc::new(
            config,
            None,
            chunks,
            tally,
            wall_s,
            Provenance::current(),
        ))
    });
    to_json(&lib(doc)?)
}

fn to_json<T: serde::Serialize>(v: &T) -> PyResult<String> {
    serde_json::to_string(v).map_err(|e| PyValueError::new_err(e.to_string()))
}

/// A simulated kernel tally (`svkernel simulate-kernels`) as the JSON text
/// of its document.
#[pyfunction]
#[pyo3(signature = (albedos, distances, g, eta, paths, seed, progress))]
#[allow(clippy::too_many_arguments)]
fn simulate_kernels(
    py: Python<'_>,
    albedos: Vec<f64>,
    distances: Vec<f64>,
    g: f64,
    eta: f64,
    paths: u64,
    seed: u64,
    progress: bool,
) -> PyResult<String> {
    let config = KernelConfig {
        albedos,
        distances,
        g,
        eta,
        paths,
        seed,
        runs: Vec::new(),
        ..svkernel::jobs::shipped::training_config()
    };
    lib(config.validate())?;
    let opts = RunOptions {
        progress,
        ..Default::default()
    };
    let doc = py.detach(|| -> svkernel::Result<KernelDoc> {
        let (tally, wall_s) = config.run(None, &opts)?;
        let chunks = vec![chunk_range(config.paths, None)];
        Ok(KernelDoc::new(
            config,
            None,
            chunks,
            tally,
            wall_s,
            Provenance::current(),
        ))
    });
    to_json(&lib(doc)?)
}

/// Fits the meta-model to a kernel tally (JSON text), from the data alone
/// or from `start`'s coefficients, and returns the model and the fit
/// report's JSON text.
#[pyfunction]
#[pyo3(signature = (tally, components, degrees, progress, start=None))]
fn fit_kernels(
    py: Python<'_>,
    tally: &str,
    components: usize,
    degrees: (usize, usize),
    progress: bool,
    start: Option<PyRef<'_, MetaModel>>,
) -> PyResult<(MetaModel, String)> {
    use svkernel::fit::meta::{FitStart, MomentFit, fit_metamodel_with};
    let doc: KernelDoc = lib(svkernel::doc::from_json(tally, Path::new("<tally>")))?;
    let start_file = start.map(|m| Arc::clone(&m.inner));
    let from = match &start_file {
        Some(f) => FitStart::From {
            model: f,
            degree: None,
        },
        None => FitStart::Ladder {
            components: components.into(),
            degree: degrees,
        },
    };
    let (model, fit) =
        lib(py.detach(|| fit_metamodel_with(&doc, &from, MomentFit::default(), progress)))?;
    let report = serde_json::json!({
        "joint": fit.joint.iter().map(|j| serde_json::json!({
            "what": j.what,
            "termination": j.termination,
            "evaluations": j.evaluations,
            "chi2_per_dof": j.chi2_per_dof,
        })).collect::<Vec<_>>(),
        "aggregation": fit.aggregation,
        "stuck": fit.stuck,
    });
    let model = MetaModel {
        inner: Arc::new(model),
        origin: "<fit>".into(),
    };
    Ok((model, report.to_string()))
}

/// Designs albedo maps for a target: `target` is (C, ny, nx) flattened.
#[pyfunction]
#[pyo3(signature = (target, channels, ny, nx, texel, albedo_range, illumination, method, iterations, warm_start, rounds, smoothness, progress, meta=None))]
#[allow(clippy::too_many_arguments)]
fn design_maps<'py>(
    py: Python<'py>,
    target: PyReadonlyArray1<'py, f64>,
    channels: usize,
    ny: usize,
    nx: usize,
    texel: f64,
    albedo_range: (f64, f64),
    illumination: &str,
    method: &str,
    iterations: usize,
    warm_start: usize,
    rounds: usize,
    smoothness: f64,
    progress: bool,
    meta: Option<PyRef<'py, MetaModel>>,
) -> PyResult<Bound<'py, PyDict>> {
    let settings = Settings {
        method: lib(Method::parse(method))?,
        texel,
        albedo_range: [albedo_range.0, albedo_range.1],
        illumination: lib(design::appearance::Illumination::parse(illumination))?,
        warm_start,
        iterations,
        rounds,
        smoothness,
        ..Settings::default()
    };
    lib(settings.validate())?;
    let values = slice(&target, "target")?;
    let target: Vec<Vec<f64>> = (0..channels)
        .map(|c| values[c * nx * ny..(c + 1) * nx * ny].to_vec())
        .collect();
    let models = models(meta.as_deref())?;
    let result = py.detach(|| {
        let task = svkernel::progress::Task::open(progress, "designing", "evaluations");
        let r = design::design(
            &target,
            nx,
            ny,
            &models.basis,
            Some(&models.meta),
            &settings,
            |done, _| task.set(done as u64),
        );
        task.finish();
        r
    });
    let d = lib(result)?;
    let dict = PyDict::new(py);
    let planes = |v: Vec<Vec<f64>>| -> PyResult<Bound<'py, PyAny>> {
        let flat: Vec<f64> = v.into_iter().flatten().collect();
        Ok(flat
            .into_pyarray(py)
            .reshape([channels, ny, nx])?
            .into_any())
    };
    dict.set_item("albedo", planes(d.albedo)?)?;
    dict.set_item("naive", planes(d.naive)?)?;
    dict.set_item("predicted", planes(d.predicted)?)?;
    dict.set_item("predicted_naive", planes(d.predicted_naive)?)?;
    dict.set_item("history", to_json(&d.history)?)?;
    dict.set_item("evaluations", d.evaluations)?;
    dict.set_item("setup_seconds", d.setup_seconds)?;
    dict.set_item("solve_seconds", d.solve_seconds)?;
    dict.set_item("stops", d.stops)?;
    Ok(dict)
}

/// The crate's version and the models' origins.
#[pyfunction]
fn info(py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
    let m = models(None)?;
    let dict = PyDict::new(py);
    dict.set_item("version", env!("CARGO_PKG_VERSION"))?;
    dict.set_item("basis", m.basis_origin.display().to_string())?;
    dict.set_item(
        "basis_diffuse",
        m.basis_diffuse_origin.display().to_string(),
    )?;
    dict.set_item("meta", m.meta_origin.display().to_string())?;
    Ok(dict)
}

#[pymodule]
fn _svkernel(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add(
        "DEFAULT_MAX_EVENTS",
        svkernel::forward::profile::DEFAULT_MAX_EVENTS,
    )?;
    m.add_function(wrap_pyfunction!(kernel, m)?)?;
    m.add_function(wrap_pyfunction!(profile, m)?)?;
    m.add_function(wrap_pyfunction!(render, m)?)?;
    m.add_function(wrap_pyfunction!(simulate_profile, m)?)?;
    m.add_function(wrap_pyfunction!(simulate_kernels, m)?)?;
    m.add_function(wrap_pyfunction!(fit_kernels, m)?)?;
    m.add_function(wrap_pyfunction!(design_maps, m)?)?;
    m.add_function(wrap_pyfunction!(info, m)?)?;
    m.add_class::<PySvBssrdf>()?;
    m.add_class::<MetaModel>()?;
    Ok(())
}
