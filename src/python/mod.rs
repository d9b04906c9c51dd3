//! pyo3 bindings: the only place that touches Python. Numpy in, numpy out; shapes are checked
//! here and reported as `ValueError`s naming the expected shape; heavy batch work runs with the
//! GIL released. The Python package (`python/acm_rs/`) normalises dtype and contiguity before
//! calling in.

mod calibration;
mod error;
mod gapfill;
mod learning;
mod tracking;

use crate::camera::{self, Camera};
use crate::emission;
use crate::error::ensure_len;
use crate::limits::StateMap;
use crate::normalization::Normalization;
use crate::rotation;
use crate::skeleton::Skeleton;
use crate::symmetry::SymmetryMap;
use error::{to_py, AcmNumericalError};
use nalgebra::{Matrix3, Vector3};
use numpy::{PyArray1, PyArrayDyn, PyArrayMethods, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use rayon::prelude::*;

type Arr<'py> = PyReadonlyArrayDyn<'py, f64>;
type IArr<'py> = PyReadonlyArrayDyn<'py, i64>;
type Out<'py> = Bound<'py, PyArrayDyn<f64>>;

/// Borrows a C-contiguous slice and checks the shape against `expected` (`None` = any size).
fn view<'a, T: numpy::Element>(
    a: &'a PyReadonlyArrayDyn<'_, T>,
    name: &str,
    expected: &[Option<usize>],
) -> PyResult<&'a [T]> {
    let shape = a.shape();
    let ok = shape.len() == expected.len()
        && shape
            .iter()
            .zip(expected)
            .all(|(s, e)| e.is_none_or(|e| e == *s));
    if !ok {
        let want: Vec<String> = expected
            .iter()
            .map(|e| e.map_or("n".to_string(), |v| v.to_string()))
            .collect();
        return Err(PyValueError::new_err(format!(
            "{name} must have shape ({}), got {shape:?}",
            want.join(", ")
        )));
    }
    a.as_slice()
        .map_err(|_| PyValueError::new_err(format!("{name} must be C-contiguous")))
}

fn out<'py>(py: Python<'py>, data: Vec<f64>, shape: &[usize]) -> PyResult<Out<'py>> {
    PyArray1::from_vec(py, data).reshape(shape.to_vec())
}

/// A new C-contiguous numpy array whose every element the caller must write (Rust fills it
/// with the GIL released; numpy's allocator uses huge pages for large outputs).
fn alloc<'py>(py: Python<'py>, shape: &[usize]) -> Out<'py> {
    // SAFETY: the array is C-contiguous and every caller overwrites all of its elements
    // before it is returned to Python; on error it is dropped unread.
    unsafe { PyArrayDyn::<f64>::new(py, shape.to_vec(), false) }
}

fn alloc_bool<'py>(py: Python<'py>, shape: &[usize]) -> Bound<'py, PyArrayDyn<bool>> {
    // SAFETY: as `alloc`; every element is written.
    unsafe { PyArrayDyn::<bool>::new(py, shape.to_vec(), false) }
}

fn vec3s(flat: &[f64]) -> Vec<Vector3<f64>> {
    flat.chunks(3)
        .map(|c| Vector3::new(c[0], c[1], c[2]))
        .collect()
}

fn mat3s(flat: &[f64]) -> Vec<Matrix3<f64>> {
    flat.chunks(9).map(Matrix3::from_row_slice).collect()
}

fn norm_from(t: f64, r: f64, px: f64, py_: f64) -> PyResult<Normalization> {
    let n = Normalization {
        translation: t,
        rotation: r,
        pixel: [px, py_],
    };
    n.validate().map_err(to_py)?;
    Ok(n)
}

/// `(n, 3)` Rodrigues vectors → `(n, 3, 3)` rotation matrices (eq. 2).
#[pyfunction]
fn rodrigues<'py>(py: Python<'py>, r: Arr<'py>) -> PyResult<Out<'py>> {
    let s = view(&r, "r", &[None, Some(3)])?;
    let n = s.len() / 3;
    let m = py.detach(|| rotation::rodrigues_batch(s)).map_err(to_py)?;
    out(py, m, &[n, 3, 3])
}

/// `(n, 3, 3)` rotation matrices → `(n, 3)` Rodrigues vectors.
#[pyfunction]
fn rodrigues_log<'py>(py: Python<'py>, mats: Arr<'py>) -> PyResult<Out<'py>> {
    let s = view(&mats, "matrices", &[None, Some(3), Some(3)])?;
    let n = s.len() / 9;
    let v = py
        .detach(|| rotation::rodrigues_log_batch(s))
        .map_err(to_py)?;
    out(py, v, &[n, 3])
}

/// `(n, 3)` Rodrigues vectors → `(n, 3, 3, 3)` derivatives `[i, a, b, k] = ∂R_ab/∂r_k`.
#[pyfunction]
fn rodrigues_jacobian<'py>(py: Python<'py>, r: Arr<'py>) -> PyResult<Out<'py>> {
    let s = view(&r, "r", &[None, Some(3)])?;
    let n = s.len() / 3;
    let d = py
        .detach(|| rotation::rodrigues_jacobian_batch(s))
        .map_err(to_py)?;
    out(py, d, &[n, 3, 3, 3])
}

/// Cameras from a `(c, 16)` parameter array, or `(c, 15)` without skew.
fn cameras_from(params: &Arr<'_>) -> PyResult<Vec<Camera>> {
    let width = match params.shape() {
        [_, w] if *w == camera::N_PARAMS_NO_SKEW => camera::N_PARAMS_NO_SKEW,
        _ => camera::N_PARAMS,
    };
    let p = view(params, "camera params", &[None, Some(width)])?;
    Camera::many_from_rows(p, width).map_err(to_py)
}

/// Projects `(n, 3)` points into `(c, 16)` cameras → `(pixels (c, n, 2), in_front (c, n))`.
#[pyfunction]
fn project<'py>(
    py: Python<'py>,
    params: Arr<'py>,
    points: Arr<'py>,
) -> PyResult<(Out<'py>, Bound<'py, PyArrayDyn<bool>>)> {
    let cams = cameras_from(&params)?;
    let pts = view(&points, "points", &[None, Some(3)])?;
    let n = pts.len() / 3;
    let pixels = alloc(py, &[cams.len(), n, 2]);
    let mask = alloc_bool(py, &[cams.len(), n]);
    {
        let mut px = pixels.readwrite();
        let mut mk = mask.readwrite();
        let (px, mk) = (px.as_slice_mut()?, mk.as_slice_mut()?);
        py.detach(|| camera::project_points_into(&cams, pts, px, Some(mk)))
            .map_err(to_py)?;
    }
    Ok((pixels, mask))
}

/// Projection with exact Jacobians → `(pixels (c, n, 2), d_point (c, n, 2, 3),
/// d_params (c, n, 2, 16))`; NaN for points behind a camera.
#[pyfunction]
fn project_jacobian<'py>(
    py: Python<'py>,
    params: Arr<'py>,
    points: Arr<'py>,
) -> PyResult<(Out<'py>, Out<'py>, Out<'py>)> {
    let cams = cameras_from(&params)?;
    let pts = view(&points, "points", &[None, Some(3)])?;
    let (c, n) = (cams.len(), pts.len() / 3);
    let j = py
        .detach(|| camera::project_points_jacobian(&cams, pts))
        .map_err(to_py)?;
    Ok((
        out(py, j.pixels, &[c, n, 2])?,
        out(py, j.d_point, &[c, n, 2, 3])?,
        out(py, j.d_params, &[c, n, 2, camera::N_PARAMS])?,
    ))
}

/// Native skeleton (tree, rest frames, lengths, offsets) with forward kinematics.
#[pyclass(frozen, name = "NativeSkeleton", module = "acm_rs._native")]
struct PySkeleton {
    inner: Skeleton,
}

#[pymethods]
impl PySkeleton {
    #[new]
    fn new(
        parents: IArr<'_>,
        rest_frames: Arr<'_>,
        lengths: Arr<'_>,
        marker_joints: IArr<'_>,
        offsets: Arr<'_>,
    ) -> PyResult<Self> {
        let par = view(&parents, "parents", &[None])?;
        let nb = par.len().saturating_sub(1);
        let frames = view(&rest_frames, "rest_frames", &[Some(nb), Some(3), Some(3)])?;
        let l = view(&lengths, "lengths", &[Some(nb)])?;
        let mj = view(&marker_joints, "marker_joints", &[None])?;
        let off = view(&offsets, "offsets", &[Some(mj.len()), Some(3)])?;
        let mj = joint_indices(mj, par.len())?;
        let inner = Skeleton::new(par, mat3s(frames), l.to_vec(), mj, vec3s(off)).map_err(to_py)?;
        Ok(Self { inner })
    }

    /// Builds the skeleton from a rest pose (see `Skeleton::from_rest_pose`).
    #[staticmethod]
    #[pyo3(signature = (parents, rest_joints, marker_joints, marker_rest, up, rest_frames=None))]
    fn from_rest_pose(
        parents: IArr<'_>,
        rest_joints: Arr<'_>,
        marker_joints: IArr<'_>,
        marker_rest: Arr<'_>,
        up: Arr<'_>,
        rest_frames: Option<Arr<'_>>,
    ) -> PyResult<Self> {
        let par = view(&parents, "parents", &[None])?;
        let rj = view(&rest_joints, "rest_joints", &[Some(par.len()), Some(3)])?;
        let mj = view(&marker_joints, "marker_joints", &[None])?;
        let mr = view(&marker_rest, "marker_rest", &[Some(mj.len()), Some(3)])?;
        let up = view(&up, "up", &[Some(3)])?;
        let nb = par.len().saturating_sub(1);
        let frames = match &rest_frames {
            Some(f) => Some(mat3s(view(
                f,
                "rest_frames",
                &[Some(nb), Some(3), Some(3)],
            )?)),
            None => None,
        };
        let mj = joint_indices(mj, par.len())?;
        let inner = Skeleton::from_rest_pose(
            par,
            &vec3s(rj),
            mj,
            &vec3s(mr),
            &Vector3::new(up[0], up[1], up[2]),
            frames,
        )
        .map_err(to_py)?;
        Ok(Self { inner })
    }

    #[getter]
    fn n_bones(&self) -> usize {
        self.inner.n_bones()
    }

    #[getter]
    fn rest_frames<'py>(&self, py: Python<'py>) -> PyResult<Out<'py>> {
        let mut v = vec![0.0; 9 * self.inner.n_bones()];
        for (m, o) in self.inner.rest_frames().iter().zip(v.chunks_mut(9)) {
            rotation::write_row_major(m, o);
        }
        out(py, v, &[self.inner.n_bones(), 3, 3])
    }

    #[getter]
    fn lengths<'py>(&self, py: Python<'py>) -> PyResult<Out<'py>> {
        out(py, self.inner.lengths().to_vec(), &[self.inner.n_bones()])
    }

    #[getter]
    fn offsets<'py>(&self, py: Python<'py>) -> PyResult<Out<'py>> {
        let v = self
            .inner
            .offsets()
            .iter()
            .flat_map(|o| [o.x, o.y, o.z])
            .collect();
        out(py, v, &[self.inner.n_markers(), 3])
    }

    #[getter]
    fn bones<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<i64>>> {
        let v: Vec<i64> = self
            .inner
            .bones()
            .iter()
            .flat_map(|&(s, e)| [s as i64, e as i64])
            .collect();
        PyArray1::from_vec(py, v).reshape(vec![self.inner.n_bones(), 2])
    }

    #[getter]
    fn marker_bones<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<i64>> {
        PyArray1::from_vec(
            py,
            self.inner
                .marker_bones()
                .iter()
                .map(|&b| b as i64)
                .collect(),
        )
    }

    /// `[i, j]`: the rotation of bone `i` moves bone `j`.
    fn bone_links<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<bool>>> {
        let n = self.inner.n_bones();
        PyArray1::from_vec(py, self.inner.bone_links()).reshape(vec![n, n])
    }

    /// The order in which the bone rotations apply (root first for the tree rule).
    #[getter]
    fn link_order<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<i64>> {
        let v = self.inner.link_order().iter().map(|&b| b as i64).collect();
        PyArray1::from_vec(py, v)
    }

    /// Whether the skeleton uses the tree rule (no explicit link matrix).
    #[getter]
    fn tree_links(&self) -> bool {
        self.inner.custom_links().is_none()
    }

    /// A copy with an explicit link matrix `links (n_bones, n_bones)` (`[i, j]`: the
    /// rotation of bone `i` moves bone `j`) applied in `order` (default: bone index order);
    /// `links=None` goes back to the tree rule.
    #[pyo3(signature = (links, order=None))]
    fn with_links(
        &self,
        links: Option<PyReadonlyArrayDyn<'_, bool>>,
        order: Option<IArr<'_>>,
    ) -> PyResult<Self> {
        let Some(links) = links else {
            return Ok(Self {
                inner: self.inner.clone().with_tree_links(),
            });
        };
        let n = self.inner.n_bones();
        if links.shape() != [n, n] {
            return Err(PyValueError::new_err(format!(
                "links must have shape ({n}, {n}), got {:?}",
                links.shape()
            )));
        }
        let flat: Vec<bool> = links.as_array().iter().copied().collect();
        let order = match &order {
            Some(o) => {
                let v = view(o, "order", &[Some(n)])?;
                let mut out = Vec::with_capacity(n);
                for &i in v {
                    if i < 0 {
                        return Err(PyValueError::new_err(format!(
                            "order must list bone indices 0..{n}, got {i}"
                        )));
                    }
                    out.push(i as usize);
                }
                Some(out)
            }
            None => None,
        };
        let inner = self
            .inner
            .clone()
            .with_links(&flat, order.as_deref())
            .map_err(to_py)?;
        Ok(Self { inner })
    }

    /// Batch FK: `t (T, 3)`, `r (T, n_bones, 3)` → `(joints (T, J, 3), markers (T, M, 3))`.
    #[pyo3(signature = (t, r, lengths=None, offsets=None))]
    fn forward<'py>(
        &self,
        py: Python<'py>,
        t: Arr<'py>,
        r: Arr<'py>,
        lengths: Option<Arr<'py>>,
        offsets: Option<Arr<'py>>,
    ) -> PyResult<(Out<'py>, Out<'py>)> {
        let sk = &self.inner;
        let ts = view(&t, "t", &[None, Some(3)])?;
        let n_t = ts.len() / 3;
        let rs = view(&r, "r", &[Some(n_t), Some(sk.n_bones()), Some(3)])?;
        let ls = match &lengths {
            Some(l) => Some(view(l, "lengths", &[Some(sk.n_bones())])?),
            None => None,
        };
        let os = match &offsets {
            Some(o) => Some(view(o, "offsets", &[Some(sk.n_markers()), Some(3)])?),
            None => None,
        };
        let joints = alloc(py, &[n_t, sk.n_joints(), 3]);
        let markers = alloc(py, &[n_t, sk.n_markers(), 3]);
        {
            let mut jw = joints.readwrite();
            let mut mw = markers.readwrite();
            let (jo, mo) = (jw.as_slice_mut()?, mw.as_slice_mut()?);
            py.detach(|| sk.forward_batch_into(ts, rs, ls, os, jo, mo))
                .map_err(to_py)?;
        }
        Ok((joints, markers))
    }

    /// Single-pose FK with exact Jacobians: `t (3,)`, `r (n_bones, 3)` →
    /// `(joints (J, 3), markers (M, 3), d_pose (J+M, 3, 3+3B), d_lengths (J+M, 3, B),
    /// d_offsets (M, 3, 3))`.
    #[pyo3(signature = (t, r, lengths=None, offsets=None))]
    #[allow(clippy::type_complexity)]
    fn forward_jacobian<'py>(
        &self,
        py: Python<'py>,
        t: Arr<'py>,
        r: Arr<'py>,
        lengths: Option<Arr<'py>>,
        offsets: Option<Arr<'py>>,
    ) -> PyResult<(Out<'py>, Out<'py>, Out<'py>, Out<'py>, Out<'py>)> {
        let sk = &self.inner;
        let ts = view(&t, "t", &[Some(3)])?;
        let rs = view(&r, "r", &[Some(sk.n_bones()), Some(3)])?;
        let ls = match &lengths {
            Some(l) => Some(view(l, "lengths", &[Some(sk.n_bones())])?.to_vec()),
            None => None,
        };
        let os = match &offsets {
            Some(o) => Some(vec3s(view(o, "offsets", &[Some(sk.n_markers()), Some(3)])?)),
            None => None,
        };
        let jac = sk
            .forward_jacobian(
                &Vector3::new(ts[0], ts[1], ts[2]),
                &vec3s(rs),
                ls.as_deref(),
                os.as_deref(),
            )
            .map_err(to_py)?;
        let (nj, nm, nb) = (sk.n_joints(), sk.n_markers(), sk.n_bones());
        let flat = |v: &[Vector3<f64>]| v.iter().flat_map(|p| [p.x, p.y, p.z]).collect::<Vec<_>>();
        Ok((
            out(py, flat(&jac.fk.joints), &[nj, 3])?,
            out(py, flat(&jac.fk.markers), &[nm, 3])?,
            out(py, jac.d_pose, &[nj + nm, 3, sk.n_pose()])?,
            out(py, jac.d_lengths, &[nj + nm, 3, nb])?,
            out(py, jac.d_offsets, &[nm, 3, 3])?,
        ))
    }

    /// Fused FK + projection: `t (N, 3)`, `r (N, B, 3)` into `(C, 16)` cameras →
    /// `(C, N, M, 2)` pixels.
    fn project_poses<'py>(
        &self,
        py: Python<'py>,
        params: Arr<'py>,
        t: Arr<'py>,
        r: Arr<'py>,
    ) -> PyResult<Out<'py>> {
        let sk = &self.inner;
        let cams = cameras_from(&params)?;
        let ts = view(&t, "t", &[None, Some(3)])?;
        let n = ts.len() / 3;
        let rs = view(&r, "r", &[Some(n), Some(sk.n_bones()), Some(3)])?;
        let pixels = alloc(py, &[cams.len(), n, sk.n_markers(), 2]);
        {
            let mut pw = pixels.readwrite();
            let po = pw.as_slice_mut()?;
            py.detach(|| emission::project_poses_into(sk, &cams, ts, rs, po))
                .map_err(to_py)?;
        }
        Ok(pixels)
    }
}

fn joint_indices(idx: &[i64], n_joints: usize) -> PyResult<Vec<usize>> {
    idx.iter()
        .enumerate()
        .map(|(k, &j)| {
            if j < 0 || j as usize >= n_joints {
                Err(PyValueError::new_err(format!(
                    "marker {k} is attached to joint {j}, not in 0..{n_joints}"
                )))
            } else {
                Ok(j as usize)
            }
        })
        .collect()
}

fn pairs(p: &IArr<'_>, name: &str) -> PyResult<Vec<(usize, usize)>> {
    let s = view(p, name, &[None, Some(2)])?;
    s.chunks(2)
        .map(|c| {
            if c[0] < 0 || c[1] < 0 {
                Err(PyValueError::new_err(format!(
                    "{name}: negative index in pair {c:?}"
                )))
            } else {
                Ok((c[0] as usize, c[1] as usize))
            }
        })
        .collect()
}

/// Left/right symmetry maps (Alg. 2-3).
#[pyclass(frozen, name = "NativeSymmetry", module = "acm_rs._native")]
struct PySymmetry {
    inner: SymmetryMap,
}

#[pymethods]
impl PySymmetry {
    #[new]
    fn new(
        n_bones: usize,
        bone_pairs: IArr<'_>,
        n_markers: usize,
        marker_pairs: IArr<'_>,
    ) -> PyResult<Self> {
        let bp = pairs(&bone_pairs, "bone_pairs")?;
        let mp = pairs(&marker_pairs, "marker_pairs")?;
        let inner = SymmetryMap::new(n_bones, &bp, n_markers, &mp).map_err(to_py)?;
        Ok(Self { inner })
    }
    #[getter]
    fn n_reduced_bones(&self) -> usize {
        self.inner.n_reduced_bones()
    }
    #[getter]
    fn n_reduced_markers(&self) -> usize {
        self.inner.n_reduced_markers()
    }
    fn expand_lengths<'py>(&self, py: Python<'py>, l: Arr<'py>) -> PyResult<Out<'py>> {
        let v = self
            .inner
            .expand_lengths(view(&l, "reduced lengths", &[None])?)
            .map_err(to_py)?;
        let n = v.len();
        out(py, v, &[n])
    }
    fn expand_offsets<'py>(&self, py: Python<'py>, v: Arr<'py>) -> PyResult<Out<'py>> {
        let s = view(&v, "reduced offsets", &[None, Some(3)])?;
        let e = self.inner.expand_offsets(s).map_err(to_py)?;
        let n = e.len() / 3;
        out(py, e, &[n, 3])
    }
    fn reduce_lengths<'py>(&self, py: Python<'py>, l: Arr<'py>) -> PyResult<Out<'py>> {
        let v = self
            .inner
            .reduce_lengths(view(&l, "lengths", &[None])?)
            .map_err(to_py)?;
        let n = v.len();
        out(py, v, &[n])
    }
    fn reduce_offsets<'py>(&self, py: Python<'py>, v: Arr<'py>) -> PyResult<Out<'py>> {
        let e = self
            .inner
            .reduce_offsets(view(&v, "offsets", &[None, Some(3)])?)
            .map_err(to_py)?;
        let n = e.len() / 3;
        out(py, e, &[n, 3])
    }
    fn reduce_length_grad<'py>(&self, py: Python<'py>, g: Arr<'py>) -> PyResult<Out<'py>> {
        let v = self
            .inner
            .reduce_length_grad(view(&g, "gradient", &[None])?)
            .map_err(to_py)?;
        let n = v.len();
        out(py, v, &[n])
    }
    fn reduce_offset_grad<'py>(&self, py: Python<'py>, g: Arr<'py>) -> PyResult<Out<'py>> {
        let e = self
            .inner
            .reduce_offset_grad(view(&g, "gradient", &[None, Some(3)])?)
            .map_err(to_py)?;
        let n = e.len() / 3;
        out(py, e, &[n, 3])
    }
}

/// State ↔ pose map with joint limits (Alg. 10).
#[pyclass(frozen, name = "NativeStateMap", module = "acm_rs._native")]
struct PyStateMap {
    inner: StateMap,
    norm: Normalization,
}

#[pymethods]
impl PyStateMap {
    /// `stretch`: elastic bones whose log-stretch follows the pose entries (issue 28).
    #[new]
    #[pyo3(signature = (lower, upper, norm, enforce, stretch=None))]
    fn new(
        lower: Arr<'_>,
        upper: Arr<'_>,
        norm: (f64, f64, f64, f64),
        enforce: bool,
        stretch: Option<IArr<'_>>,
    ) -> PyResult<Self> {
        let lo = view(&lower, "lower", &[None, Some(3)])?;
        let hi = view(&upper, "upper", &[Some(lo.len() / 3), Some(3)])?;
        let norm = norm_from(norm.0, norm.1, norm.2, norm.3)?;
        let bones = tracking::bone_list(stretch.as_ref())?;
        let inner = StateMap::new(lo.len() / 3, lo, hi, &norm, enforce)
            .and_then(|m| m.with_stretch(&bones))
            .map_err(to_py)?;
        Ok(Self { inner, norm })
    }
    #[getter]
    fn free_indices<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<i64>> {
        PyArray1::from_vec(
            py,
            self.inner
                .free_indices()
                .iter()
                .map(|&i| i as i64)
                .collect(),
        )
    }
    #[getter]
    fn n_state(&self) -> usize {
        self.inner.n_state()
    }
    /// `(N, n_state)` → `(pose (N, n_pose), d (N, n_state))` with the diagonal derivative.
    fn to_pose<'py>(&self, py: Python<'py>, z: Arr<'py>) -> PyResult<(Out<'py>, Out<'py>)> {
        let ns = self.inner.n_state();
        let s = view(&z, "z", &[None, Some(ns)])?;
        let n = s.len() / ns;
        let mut poses = Vec::with_capacity(n * self.inner.n_pose());
        let mut ds = Vec::with_capacity(n * ns);
        for row in s.chunks(ns) {
            let (p, d) = self.inner.to_pose_jacobian(row).map_err(to_py)?;
            poses.extend(p);
            ds.extend(d);
        }
        Ok((
            out(py, poses, &[n, self.inner.n_pose()])?,
            out(py, ds, &[n, ns])?,
        ))
    }
    /// `(N, n_pose)` → `(N, n_state)`.
    fn to_state<'py>(&self, py: Python<'py>, pose: Arr<'py>) -> PyResult<Out<'py>> {
        let np = self.inner.n_pose();
        let s = view(&pose, "pose", &[None, Some(np)])?;
        let n = s.len() / np;
        let mut zs = Vec::with_capacity(n * self.inner.n_state());
        for row in s.chunks(np) {
            zs.extend(self.inner.from_pose(row).map_err(to_py)?);
        }
        out(py, zs, &[n, self.inner.n_state()])
    }
    /// Forward kinematics of states `(N, n_state)` → `(joints (N, J, 3), markers (N, M, 3))`,
    /// with each state's bone lengths (elastic bones stretched by their log-stretch entries).
    fn forward<'py>(
        &self,
        py: Python<'py>,
        skeleton: &PySkeleton,
        states: Arr<'py>,
    ) -> PyResult<(Out<'py>, Out<'py>)> {
        let sk = &skeleton.inner;
        ensure_len(self.inner.n_pose(), sk.n_pose(), "state map pose length").map_err(to_py)?;
        let ns = self.inner.n_state();
        let s = view(&states, "states", &[None, Some(ns)])?;
        crate::error::ensure_finite(s, "states").map_err(to_py)?;
        let n = s.len() / ns.max(1);
        let (nj, nm) = (sk.n_joints(), sk.n_markers());
        let joints = alloc(py, &[n, nj, 3]);
        let markers = alloc(py, &[n, nm, 3]);
        {
            let mut jw = joints.readwrite();
            let mut mw = markers.readwrite();
            let (jo, mo) = (jw.as_slice_mut()?, mw.as_slice_mut()?);
            let map = &self.inner;
            py.detach(|| {
                jo.par_chunks_mut(nj * 3)
                    .zip(mo.par_chunks_mut(nm * 3))
                    .zip(s.par_chunks(ns.max(1)))
                    .for_each_init(
                        || {
                            (
                                sk.workspace(),
                                vec![0.0; sk.n_pose()],
                                vec![0.0; sk.n_bones()],
                            )
                        },
                        |(ws, pose, len), ((j, m), z)| {
                            emission::state_forward_into(sk, map, z, ws, pose, len, Some(j), m);
                        },
                    )
            });
        }
        Ok((joints, markers))
    }

    /// Alg. 4: states `(N, n_state)` → normalised pixels `(N, C, M, 2)`.
    fn emission<'py>(
        &self,
        py: Python<'py>,
        skeleton: &PySkeleton,
        params: Arr<'py>,
        states: Arr<'py>,
    ) -> PyResult<Out<'py>> {
        let cams = cameras_from(&params)?;
        let ns = self.inner.n_state();
        let s = view(&states, "states", &[None, Some(ns)])?;
        let n = s.len() / ns;
        let sk = &skeleton.inner;
        let g = py
            .detach(|| emission::emission_batch(sk, &cams, &self.inner, &self.norm, s))
            .map_err(to_py)?;
        out(py, g, &[n, cams.len(), sk.n_markers(), 2])
    }
}

/// The native module `acm_rs._native`.
#[pymodule]
#[pyo3(name = "_native")]
fn native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(rodrigues, m)?)?;
    m.add_function(wrap_pyfunction!(rodrigues_log, m)?)?;
    m.add_function(wrap_pyfunction!(rodrigues_jacobian, m)?)?;
    m.add_function(wrap_pyfunction!(project, m)?)?;
    m.add_function(wrap_pyfunction!(project_jacobian, m)?)?;
    m.add_class::<PySkeleton>()?;
    m.add_class::<PySymmetry>()?;
    m.add_class::<PyStateMap>()?;
    m.add_class::<learning::PyLearning>()?;
    m.add_class::<tracking::PyTracker>()?;
    m.add_class::<tracking::PyBufferPool>()?;
    m.add_class::<tracking::PyOnlineTracker>()?;
    m.add_function(wrap_pyfunction!(tracking::smooth_bundle, m)?)?;
    m.add_function(wrap_pyfunction!(tracking::extrapolate_params, m)?)?;
    m.add_class::<calibration::PyCalibration>()?;
    m.add("AcmNumericalError", m.py().get_type::<AcmNumericalError>())?;
    m.add("N_CAMERA_PARAMS", camera::N_PARAMS)?;
    m.add("DEFAULT_OVERRELAX", crate::tracking::DEFAULT_OVERRELAX)?;
    m.add("MAX_OVERRELAX", crate::tracking::MAX_OVERRELAX)?;
    gapfill::register(m)?;
    Ok(())
}
