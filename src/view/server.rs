//! The HTTP server of `gonio view` (axum on tokio).
//!
//! **Security model.**
//! * It binds loopback by default; another address needs `allow_remote` (the CLI warns).
//! * Every request needs the random token printed with the URL: `?token=…` on the first
//!   visit, after which it is an `HttpOnly; SameSite=Strict` cookie. Wrong or missing:
//!   401. Comparison in constant time.
//! * Only files of the served PATH are reachable, and only through `/api/file?path=REL`:
//!   the decoded `REL` must be relative, without `..`, backslash, NUL or `%` (a `%` left
//!   after decoding means double encoding), and its canonical path must stay inside the
//!   canonical PATH (a symlink out is refused). Raw request paths containing `..`,
//!   `%2e`, `%2f`, `%5c` or `%25` are refused before routing.
//! * Requests are bounded: URI ≤ 4096 bytes, body ≤ 1 KiB (only GET is routed), at most
//!   [`MAX_CONCURRENT`] requests served at once (others wait, then 503), at most
//!   [`MAX_STREAMS`] live event streams, and API renders ≤ [`MAX_API_PIXELS`].
//! * Every response carries a Content-Security-Policy (scripts and data only from the
//!   server itself), `nosniff`, `no-referrer` (the token must not leak) and `no-store`.
//! * Malformed parameters get 400 with a message naming the parameter; work is done off
//!   the async threads (`spawn_blocking`).

use super::abrdf_cache::{self, Caches, Lookup};
use super::monitor;
use super::params::{self, ParamError};
use super::render::{self, Scene, Shape};
use super::source::{RawModel, Source, SourceError, SourceKind};
use axum::body::Body;
use axum::extract::{Query, Request, State};
use axum::http::{header, HeaderValue, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use gonio_btf::compress::interp::{reconstruct_at, AnyModel, BtfModel};
use gonio_btf::compress::{CodecId, CompressedBtf, Layout};
use serde_json::Value;
use std::collections::BTreeMap;
use std::net::{IpAddr, SocketAddr};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// Requests served at once.
pub const MAX_CONCURRENT: usize = 16;
/// Live server-sent event streams.
pub const MAX_STREAMS: usize = 8;
/// Largest picture `/api/render` draws (`gonio render` has no such bound).
pub const MAX_API_PIXELS: usize = 512 * 512;
/// Longest request URI.
pub const MAX_URI: usize = 4096;
/// Decoded values an ABRDF request may read from a non-factor model.
const MAX_ABRDF_WORK: usize = 1 << 28;

const CSP: &str = "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' blob: data:; \
                   connect-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'";
const COOKIE: &str = "gonio_token";

/// Errors of starting the server.
#[derive(Debug, thiserror::Error)]
pub enum ViewError {
    #[error(transparent)]
    Source(#[from] SourceError),
    #[error(
        "refusing to bind {addr}: it is not a loopback address, and the viewer serves the data \
         to anyone who can reach it; pass --allow-remote to do it anyway"
    )]
    RemoteRefused { addr: IpAddr },
    #[error("binding {addr}: {source}")]
    Bind {
        addr: SocketAddr,
        #[source]
        source: std::io::Error,
    },
    #[error("--cache {path}: {why}")]
    Cache { path: PathBuf, why: String },
    #[error("--model {path}: {why}")]
    Model { path: PathBuf, why: String },
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

/// How to serve.
#[derive(Clone, Debug)]
pub struct ViewOptions {
    pub path: PathBuf,
    pub bind: IpAddr,
    pub port: u16,
    pub allow_remote: bool,
    /// A fixed token (tests); `None`: 128 random bits.
    pub token: Option<String>,
    /// Root of the ABRDF caches of raw datasets (`--cache DIR`); `None`:
    /// [`abrdf_cache::default_root`]. Refused inside the served dataset.
    pub cache_dir: Option<PathBuf>,
}

/// An API error: status and a plain-text message.
#[derive(Debug)]
pub struct ApiError(pub StatusCode, pub String);

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        (
            self.0,
            [(header::CONTENT_TYPE, "text/plain; charset=utf-8")],
            self.1 + "\n",
        )
            .into_response()
    }
}
impl From<ParamError> for ApiError {
    fn from(e: ParamError) -> Self {
        ApiError(StatusCode::BAD_REQUEST, e.to_string())
    }
}
fn bad(msg: impl Into<String>) -> ApiError {
    ApiError(StatusCode::BAD_REQUEST, msg.into())
}
fn internal(msg: impl std::fmt::Display) -> ApiError {
    ApiError(StatusCode::INTERNAL_SERVER_ERROR, msg.to_string())
}

type ApiResult = Result<Response, ApiError>;

/// The opened source, re-opened when a dataset's journal grows.
struct Loaded {
    journal_bytes: u64,
    source: Arc<Source>,
}

struct AppState {
    /// Canonical served path (a dataset directory or a file).
    root: PathBuf,
    kind: SourceKind,
    token: String,
    loaded: Mutex<Loaded>,
    /// `--model FILE`: a compressed file of the served dataset, shown next to it.
    model: Option<Arc<AnyModel>>,
    permits: tokio::sync::Semaphore,
    streams: AtomicUsize,
    /// The texel-major ABRDF caches of a raw dataset.
    caches: Arc<Caches>,
}

impl AppState {
    fn source(&self) -> Result<Arc<Source>, ApiError> {
        Ok(self.loaded()?.0)
    }

    /// The source and the journal length it was opened at.
    fn loaded(&self) -> Result<(Arc<Source>, u64), ApiError> {
        let mut l = self.loaded.lock().unwrap_or_else(|e| e.into_inner());
        if self.kind == SourceKind::Dataset {
            let n = monitor::journal_len(&self.root);
            if n != l.journal_bytes {
                let s = Source::open(&self.root).map_err(internal)?;
                *l = Loaded {
                    journal_bytes: n,
                    source: Arc::new(s),
                };
            }
        }
        Ok((l.source.clone(), l.journal_bytes))
    }
}

/// A bound, not yet running server.
pub struct Bound {
    pub addr: SocketAddr,
    pub token: String,
    listener: tokio::net::TcpListener,
    app: Router,
}

impl Bound {
    /// `http://ADDR/?token=…`.
    pub fn url(&self) -> String {
        format!("http://{}/?token={}", self.addr, self.token)
    }
    /// Serve until the future is dropped or the process ends.
    pub async fn serve(self) -> std::io::Result<()> {
        axum::serve(self.listener, self.app).await
    }
}

fn random_token() -> Result<String, ViewError> {
    use std::io::Read;
    let mut b = [0u8; 16];
    let p = Path::new("/dev/urandom");
    std::fs::File::open(p)
        .and_then(|mut f| f.read_exact(&mut b))
        .map_err(|source| ViewError::Io {
            path: p.to_path_buf(),
            source,
        })?;
    Ok(b.iter().map(|x| format!("{x:02x}")).collect())
}

/// Open the source and bind the socket.
pub async fn bind(opts: &ViewOptions) -> Result<Bound, ViewError> {
    bind_with_model(opts, None).await
}

/// Why `model` cannot be compared with dataset `ds`, naming what differs.
pub fn model_mismatch(ds: &dyn BtfModel, model: &dyn BtfModel) -> Option<String> {
    if (ds.width(), ds.height()) != (model.width(), model.height()) {
        return Some(format!(
            "its texture is {}×{} texels, the dataset's {}×{}",
            model.width(),
            model.height(),
            ds.width(),
            ds.height()
        ));
    }
    for (which, a, b) in [
        ("light", ds.lights_deg(), model.lights_deg()),
        ("view", ds.views_deg(), model.views_deg()),
    ] {
        if a.len() != b.len() {
            return Some(format!(
                "it has {} {which} directions, the dataset {}",
                b.len(),
                a.len()
            ));
        }
        let u = |d: [f64; 2]| gonio_btf::compress::interp::unit(d);
        for (i, (x, y)) in a.iter().zip(b).enumerate() {
            let c = gonio_btf::compress::interp::dot(u(*x), u(*y)).clamp(-1.0, 1.0);
            if c.acos().to_degrees() > gonio_btf::compress::interp::SAME_DEG {
                return Some(format!(
                    "{which} {i} is ({:.2}, {:.2})° in it and ({:.2}, {:.2})° in the dataset",
                    y[0], y[1], x[0], x[1]
                ));
            }
        }
    }
    None
}

/// [`bind`], with a compressed file (`gonio view DATASET --model FILE`) whose
/// reconstructions the inspect page shows next to the dataset's measurements and truth.
/// The file must be a `.gbtf` or `.btf` of the same texture size and directions.
pub async fn bind_with_model(opts: &ViewOptions, model: Option<&Path>) -> Result<Bound, ViewError> {
    if !opts.bind.is_loopback() && !opts.allow_remote {
        return Err(ViewError::RemoteRefused { addr: opts.bind });
    }
    let source = Source::open(&opts.path)?;
    let model = match model {
        None => None,
        Some(p) => {
            let err = |why: String| ViewError::Model {
                path: p.to_path_buf(),
                why,
            };
            if source.kind() != SourceKind::Dataset {
                return Err(err(format!(
                    "{} is not a dataset directory; --model compares a compressed file with its source dataset",
                    opts.path.display()
                )));
            }
            let m = match Source::open(p).map_err(|e| err(e.to_string()))? {
                Source::Model { model, .. } => model,
                Source::Dataset(_) => {
                    return Err(err(
                        "a dataset directory; expected a .gbtf or a UBO2014 .btf file".into()
                    ))
                }
            };
            if let Some(why) = model_mismatch(source.model(), m.model()) {
                return Err(err(format!(
                    "does not match the dataset {}: {why}",
                    opts.path.display()
                )));
            }
            Some(Arc::new(m))
        }
    };
    let root = opts.path.canonicalize().map_err(|source| ViewError::Io {
        path: opts.path.clone(),
        source,
    })?;
    let token = match &opts.token {
        Some(t) => t.clone(),
        None => random_token()?,
    };
    let cache_root = match &opts.cache_dir {
        Some(c) => Some(outside(c, &root)?),
        None => abrdf_cache::default_root().filter(|c| outside(c, &root).is_ok()),
    };
    let state = Arc::new(AppState {
        kind: source.kind(),
        loaded: Mutex::new(Loaded {
            journal_bytes: monitor::journal_len(&root),
            source: Arc::new(source),
        }),
        root,
        model,
        token: token.clone(),
        permits: tokio::sync::Semaphore::new(MAX_CONCURRENT),
        streams: AtomicUsize::new(0),
        caches: Caches::new(cache_root),
    });
    let app = router(state);
    let addr = SocketAddr::new(opts.bind, opts.port);
    let listener = tokio::net::TcpListener::bind(addr)
        .await
        .map_err(|source| ViewError::Bind { addr, source })?;
    let addr = listener
        .local_addr()
        .map_err(|source| ViewError::Bind { addr, source })?;
    Ok(Bound {
        addr,
        token,
        listener,
        app,
    })
}

/// `cache` as an absolute path (its nearest existing ancestor canonicalized), refused if
/// it lies inside the served dataset `root`: the dataset has one writer, and
/// `gonio acquire --resume` removes files it does not know.
fn outside(cache: &Path, root: &Path) -> Result<PathBuf, ViewError> {
    let err = |why: String| ViewError::Cache {
        path: cache.to_path_buf(),
        why,
    };
    let abs = std::path::absolute(cache).map_err(|e| err(format!("not a usable path ({e})")))?;
    let mut base = abs.as_path();
    let mut rest = Vec::new();
    let canon = loop {
        if let Ok(c) = base.canonicalize() {
            break c;
        }
        match (base.parent(), base.file_name()) {
            (Some(p), Some(n)) => {
                rest.push(n.to_os_string());
                base = p;
            }
            _ => break abs.clone(),
        }
    };
    let full = rest.iter().rev().fold(canon, |p, n| p.join(n));
    if full.starts_with(root) && root.is_dir() {
        return Err(err(format!(
            "is inside the served dataset {}; the cache must live outside it (its files would be \
             taken for the dataset's, and `gonio acquire --resume` removes them): pick a directory elsewhere",
            root.display()
        )));
    }
    Ok(full)
}

macro_rules! asset {
    ($name:literal, $ctype:literal) => {
        get(|| async {
            (
                [(header::CONTENT_TYPE, $ctype)],
                include_str!(concat!("assets/", $name)),
            )
        })
    };
}

fn router(state: Arc<AppState>) -> Router {
    Router::new()
        .route("/", asset!("relight.html", "text/html; charset=utf-8"))
        .route("/inspect", asset!("inspect.html", "text/html; charset=utf-8"))
        .route("/monitor", asset!("monitor.html", "text/html; charset=utf-8"))
        .route("/assets/style.css", asset!("style.css", "text/css; charset=utf-8"))
        .route(
            "/assets/common.js",
            asset!("common.js", "text/javascript; charset=utf-8"),
        )
        .route(
            "/assets/relight.js",
            asset!("relight.js", "text/javascript; charset=utf-8"),
        )
        .route(
            "/assets/inspect.js",
            asset!("inspect.js", "text/javascript; charset=utf-8"),
        )
        .route(
            "/assets/monitor.js",
            asset!("monitor.js", "text/javascript; charset=utf-8"),
        )
        .route("/favicon.ico", get(|| async { StatusCode::NO_CONTENT }))
        .route("/api/info", get(info))
        .route("/api/factors", get(factors))
        .route("/api/raw", get(raw_view))
        .route("/api/raw_pairs", get(raw_pairs))
        .route("/api/needed", get(needed))
        .route("/api/render", get(render_png))
        .route("/api/image", get(image_png))
        .route("/api/pair", get(pair_png))
        .route("/api/compare", get(compare))
        .route("/api/heat", get(heat_png))
        .route("/api/abrdf", get(abrdf))
        .route("/api/file", get(file))
        .route("/api/frame", get(frame_png))
        .route("/api/monitor", get(monitor_json))
        .route("/api/events", get(events))
        .fallback(|| async { ApiError(StatusCode::NOT_FOUND, "no such page or API".into()) })
        .layer(axum::extract::DefaultBodyLimit::max(1024))
        .layer(axum::middleware::from_fn_with_state(state.clone(), guard))
        .with_state(state)
}

fn ct_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

fn query_token(q: &str) -> Option<&str> {
    q.split('&').find_map(|kv| kv.strip_prefix("token="))
}

fn cookie_token(req: &Request) -> Option<String> {
    req.headers()
        .get_all(header::COOKIE)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(';'))
        .find_map(|c| c.trim().strip_prefix(&format!("{COOKIE}=")).map(str::to_string))
}

/// Limits, traversal refusal, token, concurrency and response headers, for every request.
async fn guard(State(st): State<Arc<AppState>>, req: Request, next: Next) -> Response {
    let mut resp = guarded(&st, req, next).await;
    let h = resp.headers_mut();
    h.insert(header::CONTENT_SECURITY_POLICY, HeaderValue::from_static(CSP));
    h.insert(header::X_CONTENT_TYPE_OPTIONS, HeaderValue::from_static("nosniff"));
    h.insert(header::REFERRER_POLICY, HeaderValue::from_static("no-referrer"));
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    resp
}

async fn guarded(st: &AppState, req: Request, next: Next) -> Response {
    let uri = req.uri().clone();
    if uri.to_string().len() > MAX_URI {
        return ApiError(
            StatusCode::URI_TOO_LONG,
            format!("request URI longer than {MAX_URI} bytes"),
        )
        .into_response();
    }
    let raw_path = uri.path().to_ascii_lowercase();
    if raw_path.contains("..")
        || ["%2e", "%2f", "%5c", "%25", "%00", "\\", "//"]
            .iter()
            .any(|p| raw_path.contains(p))
    {
        return bad(format!(
            "request path {:?} refused: `..`, encoded dots or slashes and double encoding are not served",
            uri.path().chars().take(80).collect::<String>()
        ))
        .into_response();
    }
    if req.method() != axum::http::Method::GET && req.method() != axum::http::Method::HEAD {
        return ApiError(
            StatusCode::METHOD_NOT_ALLOWED,
            "the viewer is read-only: GET only".into(),
        )
        .into_response();
    }
    let from_query = uri.query().and_then(query_token).map(str::to_string);
    let ok = |t: &Option<String>| t.as_deref().is_some_and(|t| ct_eq(t.as_bytes(), st.token.as_bytes()));
    let via_query = ok(&from_query);
    if !via_query && !ok(&cookie_token(&req)) {
        return ApiError(
            StatusCode::UNAUTHORIZED,
            "missing or wrong access token: open the URL that `gonio view` printed".into(),
        )
        .into_response();
    }
    let _permit = match tokio::time::timeout(Duration::from_secs(30), st.permits.acquire()).await {
        Ok(Ok(p)) => p,
        _ => {
            return ApiError(
                StatusCode::SERVICE_UNAVAILABLE,
                "too many requests at once; retry".into(),
            )
            .into_response()
        }
    };
    let mut resp = next.run(req).await;
    if via_query {
        let c = format!("{COOKIE}={}; HttpOnly; SameSite=Strict; Path=/", st.token);
        if let Ok(v) = HeaderValue::from_str(&c) {
            resp.headers_mut().insert(header::SET_COOKIE, v);
        }
    }
    resp
}

type Q = Query<BTreeMap<String, String>>;

fn get_param<'a>(q: &'a BTreeMap<String, String>, name: &str) -> Result<&'a str, ApiError> {
    q.get(name)
        .map(String::as_str)
        .ok_or_else(|| bad(format!("parameter `{name}` is missing")))
}
fn opt_param<'a>(q: &'a BTreeMap<String, String>, name: &str, default: &'a str) -> &'a str {
    q.get(name).map(String::as_str).unwrap_or(default)
}

/// Run blocking work off the async threads.
async fn blocking<F>(f: F) -> ApiResult
where
    F: FnOnce() -> ApiResult + Send + 'static,
{
    tokio::task::spawn_blocking(f)
        .await
        .unwrap_or_else(|e| Err(internal(format!("worker failed: {e}"))))
}

fn png_response(bytes: Vec<u8>) -> Response {
    ([(header::CONTENT_TYPE, "image/png")], bytes).into_response()
}
fn json_response<T: serde::Serialize>(v: &T) -> ApiResult {
    let body = serde_json::to_vec(v).map_err(internal)?;
    Ok(([(header::CONTENT_TYPE, "application/json")], body).into_response())
}
fn bytes_response(bytes: Vec<u8>) -> Response {
    ([(header::CONTENT_TYPE, "application/octet-stream")], bytes).into_response()
}

/// How the page decodes the source on the GPU.
fn gpu_kind(src: &Source) -> Option<&'static str> {
    match src {
        Source::Dataset(_) => Some("raw"),
        Source::Model {
            model: AnyModel::Gbtf(m),
            ..
        } => match m.layout() {
            // `gpu_blocks`, decoded by the page's shader named after the method.
            Layout::Basis | Layout::ViewBases | Layout::Clusters { .. } => Some(m.method().name()),
            Layout::Index { .. }
            | Layout::ChannelFactors
            | Layout::HalfVectorTables { .. }
            | Layout::PerTexel
            | Layout::AnalyticPerTexel => super::gpu::kind(src).map(super::gpu::Kind::name),
        },
        Source::Model { .. } => super::gpu::kind(src).map(super::gpu::Kind::name),
    }
}

async fn info(State(st): State<Arc<AppState>>) -> ApiResult {
    let src = st.source()?;
    let m = src.model();
    let (method, components, blocks) = match &*src {
        Source::Model {
            model: AnyModel::Gbtf(g),
            ..
        } => (g.method().name(), g.components(), gpu_block_count(g)),
        Source::Model {
            model: AnyModel::Dfmf(_),
            ..
        } => (CodecId::Dfmf.name(), 0, 0),
        Source::Dataset(_) => ("raw", 0, 0),
    };
    // Columns of the GPU blocks (local PCA: 1, the coefficients, the cluster index) and
    // clusters (1 but for local PCA).
    let (gpu_cols, clusters) = match &*src {
        Source::Model {
            model: AnyModel::Gbtf(g),
            ..
        } => match g.layout() {
            Layout::Clusters { clusters } => (components + 2, clusters),
            Layout::Basis
            | Layout::ViewBases
            | Layout::Index { .. }
            | Layout::ChannelFactors
            | Layout::HalfVectorTables { .. }
            | Layout::PerTexel
            | Layout::AnalyticPerTexel => (components, 1),
        },
        Source::Model { .. } | Source::Dataset(_) => (components, 1),
    };
    let truth = match &*src {
        Source::Dataset(d) => d.views.dir.join("truth").is_dir(),
        _ => false,
    };
    let measured: Vec<[usize; 2]> = match &*src {
        Source::Dataset(d) => (0..d.views.n_views())
            .flat_map(|v| (0..d.views.n_lights()).map(move |l| (l, v)))
            .filter(|&(l, v)| d.views.is_measured(l, v))
            .map(|(l, v)| [l, v])
            .collect(),
        _ => Vec::new(),
    };
    let mut v = serde_json::json!({
        "kind": st.kind,
        "method": method,
        "gpu": gpu_kind(&src),
        "components": components,
        "blocks": blocks,
        "gpu_cols": gpu_cols,
        "clusters": clusters,
        "width": m.width(),
        "height": m.height(),
        "lights_deg": m.lights_deg(),
        "views_deg": m.views_deg(),
        "truth": truth,
        "model": st.model.as_ref().map(|m| match &**m {
            AnyModel::Gbtf(g) => g.method().name(),
            AnyModel::Dfmf(_) => CodecId::Dfmf.name(),
        }),
        "measured_pairs": measured,
        "max_api_pixels": MAX_API_PIXELS,
    });
    if let Some(k) = super::gpu::kind(&src) {
        if let (Some(o), Value::Object(extra)) = (v.as_object_mut(), super::gpu::describe(&src, k)) {
            o.extend(extra);
        }
    }
    json_response(&v)
}

/// f16 little-endian values of a matrix with `cols` columns padded to a multiple of 4.
fn f16_padded(data: &[f32], cols: usize) -> Vec<u8> {
    let c4 = cols.div_ceil(4) * 4;
    let rows = data.len().checked_div(cols).unwrap_or(0);
    let mut out = Vec::with_capacity(rows * c4 * 2);
    for r in 0..rows {
        for j in 0..c4 {
            let x = if j < cols { data[r * cols + j] } else { 0.0 };
            out.extend_from_slice(&half::f16::from_f32(x).to_le_bytes());
        }
    }
    out
}
fn f32_padded(data: &[f32], cols: usize) -> Vec<u8> {
    let c4 = cols.div_ceil(4) * 4;
    let rows = data.len().checked_div(cols).unwrap_or(0);
    let mut out = Vec::with_capacity(rows * c4 * 4);
    for r in 0..rows {
        for j in 0..c4 {
            let x = if j < cols { data[r * cols + j] } else { 0.0 };
            out.extend_from_slice(&x.to_le_bytes());
        }
    }
    out
}

/// `/api/factors?block=N`: a PCA/PVMF factor block for the GPU: texel bases (even blocks)
/// as f16, weight rows (odd blocks) as f32, columns padded to a multiple of 4.
async fn factors(State(st): State<Arc<AppState>>, Query(q): Q) -> ApiResult {
    let src = st.source()?;
    if let Some(k) = super::gpu::kind(&src) {
        let i = params::index("block", get_param(&q, "block")?, super::gpu::block_count(&src, k))?;
        return blocking(move || Ok(bytes_response(super::gpu::block(&src, k, i)))).await;
    }
    let Source::Model {
        model: AnyModel::Gbtf(m),
        ..
    } = &*src
    else {
        return Err(bad("this source has no PCA/PVMF factor blocks"));
    };
    if gpu_kind(&src).is_none() {
        return Err(bad(format!(
            "method {} has no GPU decoder; use /api/render",
            m.method().name()
        )));
    }
    let n = gpu_block_count(m);
    let i = params::index("block", get_param(&q, "block")?, n)?;
    let src2 = src.clone();
    blocking(move || {
        let Source::Model {
            model: AnyModel::Gbtf(m),
            ..
        } = &*src2
        else {
            unreachable!()
        };
        let (data, cols) = gpu_blocks(m).swap_remove(i);
        Ok(bytes_response(if i % 2 == 0 {
            f16_padded(&data, cols)
        } else {
            f32_padded(&data, cols)
        }))
    })
    .await
}

/// Number of [`gpu_blocks`] (without building them).
fn gpu_block_count(m: &CompressedBtf) -> usize {
    match m.layout() {
        Layout::Clusters { .. } => 2,
        Layout::Basis | Layout::ViewBases => m.gbtf.blocks.len(),
        Layout::Index { .. }
        | Layout::ChannelFactors
        | Layout::HalfVectorTables { .. }
        | Layout::PerTexel
        | Layout::AnalyticPerTexel => 0,
    }
}

/// The factor blocks the page's shader reads, `(values, columns)`: even blocks are texel
/// bases, odd blocks weight rows. PVMF and PCA: the file's blocks. Local PCA is a PCA
/// whose rows depend on the texel's cluster: basis row `[1, coefficients…, cluster]`,
/// rows `[mean, eigen-ABRDF values…, 0]` for every (cluster, view, light, channel), so that
/// `basis · row` is `mean + Σ coef · basis` and the cluster column contributes nothing.
fn gpu_blocks(m: &CompressedBtf) -> Vec<(std::borrow::Cow<'_, [f32]>, usize)> {
    use std::borrow::Cow;
    let c = m.components();
    match m.layout() {
        Layout::Clusters { clusters: k } => {
            let h = m.header();
            let (t, dims) = (h.width * h.height, h.lights_deg.len() * h.views_deg.len() * 3);
            let (cluster, coef, mean, basis) = (
                &m.gbtf.blocks[0],
                &m.gbtf.blocks[1],
                &m.gbtf.blocks[2],
                &m.gbtf.blocks[3],
            );
            let mut b0 = Vec::with_capacity(t * (c + 2));
            for i in 0..t {
                b0.push(1.0);
                b0.extend_from_slice(&coef[i * c..(i + 1) * c]);
                b0.push(cluster[i]);
            }
            let mut b1 = Vec::with_capacity(k * dims * (c + 2));
            for j in 0..k {
                for r in 0..dims {
                    b1.push(mean[j * dims + r]);
                    b1.extend((0..c).map(|q| basis[(j * c + q) * dims + r]));
                    b1.push(0.0);
                }
            }
            vec![(Cow::Owned(b0), c + 2), (Cow::Owned(b1), c + 2)]
        }
        Layout::Basis | Layout::ViewBases => m.gbtf.blocks.iter().map(|b| (Cow::Borrowed(&b[..]), c)).collect(),
        Layout::Index { .. }
        | Layout::ChannelFactors
        | Layout::HalfVectorTables { .. }
        | Layout::PerTexel
        | Layout::AnalyticPerTexel => Vec::new(),
    }
}

/// `/api/raw?view=V`: every light's image of view V of a dataset, f16 RGBA (A = 1),
/// lights in order, unmeasured pairs filled as [`RawModel`] does.
async fn raw_view(State(st): State<Arc<AppState>>, Query(q): Q) -> ApiResult {
    let src = st.source()?;
    let Source::Dataset(d) = &*src else {
        return Err(bad("raw images exist only for a dataset directory"));
    };
    let v = params::index("view", get_param(&q, "view")?, d.views.n_views())?;
    let src2 = src.clone();
    blocking(move || {
        let Source::Dataset(d) = &*src2 else { unreachable!() };
        let mut out = Vec::with_capacity(d.views.n_lights() * d.views.texels() * 8);
        let one = half::f16::from_f32(1.0).to_le_bytes();
        for l in 0..d.views.n_lights() {
            let img = d.reconstruct(l, v).map_err(internal)?;
            for px in img.chunks_exact(3) {
                for x in px {
                    out.extend_from_slice(&half::f16::from_f32(*x).to_le_bytes());
                }
                out.extend_from_slice(&one);
            }
        }
        Ok(bytes_response(out))
    })
    .await
}

/// Grid pairs one `/api/raw_pairs` request may ask for.
pub const MAX_PAIRS_PER_REQUEST: usize = 16;
/// Largest `/api/raw_pairs` response.
pub const MAX_RAW_RESPONSE: usize = 64 << 20;

/// `/api/raw_pairs?pairs=L.V,L.V,…`: the images of up to [`MAX_PAIRS_PER_REQUEST`] grid
/// pairs of a dataset (at most [`MAX_RAW_RESPONSE`] bytes), f16 RGB, in the order asked,
/// unmeasured pairs filled as [`RawModel`] does. The relight page streams a large raw
/// dataset with it, the images of the current picture first.
async fn raw_pairs(State(st): State<Arc<AppState>>, Query(q): Q) -> ApiResult {
    let src = st.source()?;
    let Source::Dataset(d) = &*src else {
        return Err(bad("raw images exist only for a dataset directory"));
    };
    let (nl, nv) = (d.views.n_lights(), d.views.n_views());
    let list = get_param(&q, "pairs")?;
    let mut pairs = Vec::new();
    for item in list.split(',') {
        let (l, v) = item
            .split_once('.')
            .ok_or_else(|| bad(format!("parameter `pairs`: {item:?} is not LIGHT.VIEW")))?;
        pairs.push((
            params::index("pairs (light)", l, nl)?,
            params::index("pairs (view)", v, nv)?,
        ));
    }
    if pairs.len() > MAX_PAIRS_PER_REQUEST {
        return Err(bad(format!(
            "parameter `pairs`: {} pairs, at most {MAX_PAIRS_PER_REQUEST} per request",
            pairs.len()
        )));
    }
    let bytes = pairs.len() * d.views.texels() * 6;
    if bytes > MAX_RAW_RESPONSE {
        return Err(bad(format!(
            "parameter `pairs`: {} images of {}×{} are {bytes} bytes, at most {MAX_RAW_RESPONSE} per request",
            pairs.len(),
            d.views.width,
            d.views.height
        )));
    }
    let src2 = src.clone();
    blocking(move || {
        let Source::Dataset(d) = &*src2 else { unreachable!() };
        let mut out = Vec::with_capacity(bytes);
        for (l, v) in pairs {
            for x in d.reconstruct(l, v).map_err(internal)? {
                out.extend_from_slice(&half::f16::from_f32(x).to_le_bytes());
            }
        }
        Ok(bytes_response(out))
    })
    .await
}

/// `/api/needed?light&view&shape&size`: the grid pairs the picture of that state uses,
/// `[light, view, weight]`, most used first (see [`render::needed_pairs`]).
async fn needed(State(st): State<Arc<AppState>>, Query(q): Q) -> ApiResult {
    let scene = scene_from_query(&q)?;
    let src = st.source()?;
    blocking(move || {
        let pairs = render::needed_pairs(src.model(), &scene).map_err(|e| bad(e.to_string()))?;
        let list: Vec<(usize, usize, f64)> = pairs;
        json_response(&serde_json::json!({ "pairs": list }))
    })
    .await
}

/// The scene of a query (the page's URL state).
pub fn scene_from_query(q: &BTreeMap<String, String>) -> Result<Scene, ApiError> {
    let light_deg = params::direction("light", opt_param(q, "light", "30,0"))?;
    let view_deg = params::direction("view", opt_param(q, "view", "0,0"))?;
    let shape: Shape = params::shape("shape", opt_param(q, "shape", "plane"))?;
    let (width, height) = params::size("size", opt_param(q, "size", "256x256"))?;
    if width * height > MAX_API_PIXELS {
        return Err(bad(format!(
            "parameter `size` = {width}x{height}: at most {MAX_API_PIXELS} pixels through the API (use `gonio render`)"
        )));
    }
    let exposure = params::exposure("exposure", opt_param(q, "exposure", "1"))?;
    Ok(Scene {
        light_deg,
        view_deg,
        shape,
        width,
        height,
        exposure,
    })
}

/// `/api/render?light&view&shape&size&exposure`: the CPU reference picture as PNG.
async fn render_png(State(st): State<Arc<AppState>>, Query(q): Q) -> ApiResult {
    let scene = scene_from_query(&q)?;
    let src = st.source()?;
    blocking(move || {
        let pic = render::render(src.model(), &scene).map_err(|e| bad(e.to_string()))?;
        Ok(png_response(
            render::png(pic.width, pic.height, &pic.srgb8).map_err(internal)?,
        ))
    })
    .await
}

fn tone_png(img: &[f32], w: usize, h: usize, exposure: f64) -> ApiResult {
    let e = exposure as f32;
    let rgb: Vec<u8> = img
        .iter()
        .map(|&x| gonio_dataset::store::linear_to_srgb8(e * x))
        .collect();
    Ok(png_response(render::png(w, h, &rgb).map_err(internal)?))
}

/// `/api/image?light=θ,φ&view=θ,φ&exposure`: the interpolated BTF image (as `gonio
/// reconstruct` makes it), tone-mapped.
async fn image_png(State(st): State<Arc<AppState>>, Query(q): Q) -> ApiResult {
    let l = params::direction("light", get_param(&q, "light")?)?;
    let v = params::direction("view", get_param(&q, "view")?)?;
    let e = params::exposure("exposure", opt_param(&q, "exposure", "1"))?;
    let src = st.source()?;
    blocking(move || {
        let m = src.model();
        let (img, _) = reconstruct_at(m, l, v).map_err(|e| bad(e.to_string()))?;
        tone_png(&img, m.width(), m.height(), e)
    })
    .await
}

/// The images of grid pair (l, v) that exist: `model` (a compressed file's decoding, or
/// the `--model` file's next to a dataset), `measured` (a dataset's stored image), `truth`
/// (a simulated dataset's stored truth).
fn pair_sources(src: &Source, model: Option<&AnyModel>, l: usize, v: usize) -> Vec<&'static str> {
    match src {
        Source::Model { .. } => vec!["model"],
        Source::Dataset(d) => {
            let mut s = Vec::new();
            if d.views.is_measured(l, v) {
                s.push("measured");
            }
            if model.is_some() {
                s.push("model");
            }
            if d.views.is_measured(l, v) && truth_path(d, l, v).is_some() {
                s.push("truth");
            }
            s
        }
    }
}

fn truth_path(d: &RawModel, l: usize, v: usize) -> Option<PathBuf> {
    let p = d.views.dir.join(format!("truth/{:05}.exr", v * d.views.n_lights() + l));
    p.is_file().then_some(p)
}

fn pair_image(src: &Source, model: Option<&AnyModel>, l: usize, v: usize, which: &str) -> Result<Vec<f32>, ApiError> {
    let have = pair_sources(src, model, l, v);
    if !have.contains(&which) {
        return Err(bad(format!(
            "parameter `source` = {which:?}: not available for pair (light {l}, view {v}); available: {have:?}"
        )));
    }
    match (src, which) {
        (Source::Dataset(d), "truth") => {
            let p = truth_path(d, l, v).ok_or_else(|| bad("no truth image"))?;
            Ok(gonio_dataset::store::read_exr(&p).map_err(internal)?.data)
        }
        (Source::Dataset(_), "model") => match model {
            Some(m) => m.model().reconstruct(l, v).map_err(internal),
            None => Err(bad("no --model file")),
        },
        _ => src.model().reconstruct(l, v).map_err(internal),
    }
}

fn grid_pair(q: &BTreeMap<String, String>, src: &Source) -> Result<(usize, usize), ApiError> {
    let m = src.model();
    let l = params::index("l", get_param(q, "l")?, m.lights_deg().len())?;
    let v = params::index("v", get_param(q, "v")?, m.views_deg().len())?;
    Ok((l, v))
}

/// `/api/pair?l=I&v=J&source=model|measured|truth&exposure`: one grid pair's image.
async fn pair_png(State(st): State<Arc<AppState>>, Query(q): Q) -> ApiResult {
    let src = st.source()?;
    let (l, v) = grid_pair(&q, &src)?;
    let which = opt_param(&q, "source", "").to_string();
    let e = params::exposure("exposure", opt_param(&q, "exposure", "1"))?;
    let model = st.model.clone();
    blocking(move || {
        let model = model.as_deref();
        let which = if which.is_empty() {
            pair_sources(&src, model, l, v)
                .first()
                .copied()
                .unwrap_or("model")
                .to_string()
        } else {
            which
        };
        let img = pair_image(&src, model, l, v, &which)?;
        let m = src.model();
        tone_png(&img, m.width(), m.height(), e)
    })
    .await
}

fn psnr(a: &[f32], reference: &[f32]) -> (f64, f64) {
    let peak = reference.iter().fold(0f32, |m, &x| m.max(x)) as f64;
    let mse = a
        .iter()
        .zip(reference)
        .map(|(x, y)| ((x - y) as f64).powi(2))
        .sum::<f64>()
        / a.len().max(1) as f64;
    let p = if mse == 0.0 {
        f64::INFINITY
    } else {
        10.0 * (peak * peak / mse).log10()
    };
    (p, mse.sqrt())
}

/// `/api/compare?l&v`: which images exist for a grid pair and the PSNR of the others
/// against each reference: truth if stored (measured and model against it), and the
/// measurement (the model against it); linear values, peak = the reference's maximum.
async fn compare(State(st): State<Arc<AppState>>, Query(q): Q) -> ApiResult {
    let src = st.source()?;
    let (l, v) = grid_pair(&q, &src)?;
    let model = st.model.clone();
    blocking(move || {
        let model = model.as_deref();
        let sources = pair_sources(&src, model, l, v);
        let mut rows = Vec::new();
        for reference in ["truth", "measured"] {
            if !sources.contains(&reference) {
                continue;
            }
            let r = pair_image(&src, model, l, v, reference)?;
            for s in ["measured", "model"] {
                if s == reference || !sources.contains(&s) {
                    continue;
                }
                let (p, rmse) = psnr(&pair_image(&src, model, l, v, s)?, &r);
                rows.push(serde_json::json!({"source": s, "reference": reference,
                    "psnr_db": if p.is_finite() { serde_json::json!(p) } else { serde_json::json!("inf") },
                    "rmse": rmse}));
            }
        }
        let m = src.model();
        json_response(&serde_json::json!({
            "l": l, "v": v,
            "light_deg": m.lights_deg()[l], "view_deg": m.views_deg()[v],
            "sources": sources, "errors": rows,
        }))
    })
    .await
}

/// `/api/heat?l&v&a&b`: |a − b| (mean over channels) as a heat map, scaled to its maximum.
async fn heat_png(State(st): State<Arc<AppState>>, Query(q): Q) -> ApiResult {
    let src = st.source()?;
    let (l, v) = grid_pair(&q, &src)?;
    let a = get_param(&q, "a")?.to_string();
    let b = get_param(&q, "b")?.to_string();
    let model = st.model.clone();
    blocking(move || {
        let model = model.as_deref();
        let (x, y) = (pair_image(&src, model, l, v, &a)?, pair_image(&src, model, l, v, &b)?);
        let err: Vec<f32> = x
            .chunks_exact(3)
            .zip(y.chunks_exact(3))
            .map(|(p, q)| ((p[0] - q[0]).abs() + (p[1] - q[1]).abs() + (p[2] - q[2]).abs()) / 3.0)
            .collect();
        let max = err.iter().fold(0f32, |m, &e| m.max(e)).max(1e-12);
        let rgb: Vec<u8> = err.iter().flat_map(|&e| heat(e / max)).collect();
        let m = src.model();
        Ok(png_response(
            render::png(m.width(), m.height(), &rgb).map_err(internal)?,
        ))
    })
    .await
}

/// Black → red → yellow → white.
fn heat(t: f32) -> [u8; 3] {
    let t = t.clamp(0.0, 1.0) * 3.0;
    let c = |x: f32| (x.clamp(0.0, 1.0) * 255.0).round() as u8;
    [c(t), c(t - 1.0), c(t - 2.0)]
}

/// `/api/abrdf?x&y`: the ABRDF of texel (x, y) as a views × lights table of RGB.
///
/// A raw dataset larger than [`RawModel::abrdf_direct`] answers from its texel-major
/// cache ([`abrdf_cache`]): `200` with `"cache": {…}` once it exists (from an earlier state
/// of a growing dataset while the present one builds, saying how many pairs it covers), or
/// `202 Accepted` with `{"building": {…}, "message": "…"}` while the first one builds (the
/// page polls).
async fn abrdf(State(st): State<Arc<AppState>>, Query(q): Q) -> ApiResult {
    let (src, journal_bytes) = st.loaded()?;
    let m = src.model();
    let x = params::index("x", get_param(&q, "x")?, m.width())?;
    let y = params::index("y", get_param(&q, "y")?, m.height())?;
    let (nl, nv) = (m.lights_deg().len(), m.views_deg().len());
    if let Source::Dataset(d) = &*src {
        if !d.abrdf_direct() {
            let caches = st.caches.clone();
            let src = src.clone();
            return blocking(move || {
                let Source::Dataset(d) = &*src else { unreachable!() };
                let cached = |c: &abrdf_cache::AbrdfCache, building: Option<&abrdf_cache::ProgressSnapshot>| {
                    let values = c.abrdf(x, y).map_err(internal)?;
                    let measured = d.views.n_measured();
                    let note = building.map(|b| {
                        format!(
                            "from the cache of an earlier state of the dataset: {} of its {measured} measured pairs; \
                             the present state's cache is {b}",
                            c.pairs()
                        )
                    });
                    json_response(&serde_json::json!({
                        "x": x, "y": y, "lights": nl, "views": nv, "values": values,
                        "cache": {"pairs": c.pairs(), "measured": measured, "current": building.is_none(),
                                  "building": building, "note": note},
                    }))
                };
                match caches.lookup(&d.views, journal_bytes).map_err(internal)? {
                    Lookup::Ready(c) => cached(&c, None),
                    Lookup::Older { cache, building } => cached(&cache, Some(&building)),
                    Lookup::Building(p) => {
                        let body = serde_json::to_vec(&serde_json::json!({
                            "x": x, "y": y,
                            "building": p,
                            "message": format!(
                                "the ABRDF cache of this dataset ({} images) is {p}; this answer is repeated until it is ready",
                                p.images_total
                            ),
                        }))
                        .map_err(internal)?;
                        Ok((StatusCode::ACCEPTED, [(header::CONTENT_TYPE, "application/json")], body).into_response())
                    }
                    Lookup::Failed(why) => Err(internal(format!(
                        "the ABRDF cache of this dataset could not be built: {why}"
                    ))),
                }
            })
            .await;
        }
    }
    // PCA and PVMF: a texel's values are its basis row times the measurement rows.
    let fast = match &*src {
        Source::Model {
            model: AnyModel::Gbtf(g),
            ..
        } => g.layout().has_bases(),
        Source::Model { .. } | Source::Dataset(_) => false,
    };
    if !fast && nl * nv * m.width() * m.height() * 3 > MAX_ABRDF_WORK {
        return Err(bad(format!(
            "an ABRDF of this source decodes {nl}×{nv} full images; too much work per click (compress it first)"
        )));
    }
    blocking(move || {
        let m = src.model();
        let t = y * m.width() + x;
        let mut values = vec![[0f32; 3]; nl * nv];
        if let Some(g) = m
            .as_any()
            .and_then(|a| a.downcast_ref::<CompressedBtf>())
            .filter(|_| fast)
        {
            let c = g.components();
            let b = &g.gbtf.blocks;
            for v in 0..nv {
                for l in 0..nl {
                    let (basis, rows, r0) = if g.layout() == Layout::ViewBases {
                        (&b[2 * v], &b[2 * v + 1], l * 3)
                    } else {
                        (&b[0], &b[1], (v * nl + l) * 3)
                    };
                    let bt = &basis[t * c..(t + 1) * c];
                    values[v * nl + l] = std::array::from_fn(|ch| {
                        let row = &rows[(r0 + ch) * c..(r0 + ch + 1) * c];
                        bt.iter().zip(row).map(|(p, q)| p * q).sum()
                    });
                }
            }
        } else {
            for v in 0..nv {
                for l in 0..nl {
                    let img = m.reconstruct(l, v).map_err(internal)?;
                    values[v * nl + l] = [img[t * 3], img[t * 3 + 1], img[t * 3 + 2]];
                }
            }
        }
        json_response(&serde_json::json!({
            "x": x, "y": y, "lights": nl, "views": nv, "values": values,
        }))
    })
    .await
}

/// Resolve a client-given relative path inside the served directory, refusing anything
/// that could leave it (see the module doc).
pub fn resolve_inside(root: &Path, rel: &str) -> Result<PathBuf, ApiError> {
    if rel.is_empty() || rel.len() > 512 {
        return Err(bad("parameter `path`: expected a relative path of 1 ..= 512 bytes"));
    }
    if rel.contains('%') {
        return Err(bad(
            "parameter `path`: a `%` after decoding (double encoding) is refused",
        ));
    }
    if rel.contains('\\') || rel.contains('\0') {
        return Err(bad("parameter `path`: backslashes and NUL are refused"));
    }
    let p = Path::new(rel);
    if p.is_absolute() || rel.starts_with('/') {
        return Err(bad(
            "parameter `path`: absolute paths are refused; give a path inside the dataset",
        ));
    }
    if !p
        .components()
        .all(|c| matches!(c, std::path::Component::Normal(_) | std::path::Component::CurDir))
    {
        return Err(bad("parameter `path`: `..` is refused; give a path inside the dataset"));
    }
    let full = root.join(p);
    let canon = full
        .canonicalize()
        .map_err(|_| ApiError(StatusCode::NOT_FOUND, format!("{rel}: no such file in the dataset")))?;
    if !canon.starts_with(root) {
        return Err(ApiError(
            StatusCode::FORBIDDEN,
            format!("{rel}: leads outside the served directory (a symlink out); refused"),
        ));
    }
    if !canon.is_file() {
        return Err(ApiError(StatusCode::NOT_FOUND, format!("{rel}: not a file")));
    }
    Ok(canon)
}

/// `/api/file?path=REL`: a file of the served dataset, as bytes.
async fn file(State(st): State<Arc<AppState>>, Query(q): Q) -> ApiResult {
    if st.kind != SourceKind::Dataset {
        return Err(ApiError(
            StatusCode::NOT_FOUND,
            "serving a single file: there are no other files to read".into(),
        ));
    }
    let p = resolve_inside(&st.root, get_param(&q, "path")?)?;
    blocking(move || {
        let bytes = std::fs::read(&p).map_err(internal)?;
        let ct = match p.extension().and_then(|e| e.to_str()) {
            Some("json") => "application/json",
            Some("jsonl") | Some("txt") | Some("csv") => "text/plain; charset=utf-8",
            Some("png") => "image/png",
            _ => "application/octet-stream",
        };
        Ok(([(header::CONTENT_TYPE, ct)], Body::from(bytes)).into_response())
    })
    .await
}

/// `/api/frame?index=N&exposure`: a stored rectified image of a dataset, tone-mapped.
async fn frame_png(State(st): State<Arc<AppState>>, Query(q): Q) -> ApiResult {
    let src = st.source()?;
    let Source::Dataset(d) = &*src else {
        return Err(bad("frames exist only for a dataset directory"));
    };
    let n = d.views.n_lights() * d.views.n_views();
    let i = params::index("index", get_param(&q, "index")?, n)?;
    let e = params::exposure("exposure", opt_param(&q, "exposure", "1"))?;
    let (l, v) = (i % d.views.n_lights(), i / d.views.n_lights());
    if !d.views.is_measured(l, v) {
        return Err(ApiError(
            StatusCode::NOT_FOUND,
            format!("measurement {i} has no image (yet)"),
        ));
    }
    let src2 = src.clone();
    blocking(move || {
        let Source::Dataset(d) = &*src2 else { unreachable!() };
        let img = d.views.read_image(l, v).map_err(internal)?.unwrap_or_default();
        tone_png(&img, d.views.width, d.views.height, e)
    })
    .await
}

async fn monitor_json(State(st): State<Arc<AppState>>) -> ApiResult {
    if st.kind != SourceKind::Dataset {
        return Err(bad("the monitor needs a dataset directory"));
    }
    let root = st.root.clone();
    blocking(move || json_response(&monitor::snapshot(&root).map_err(internal)?)).await
}

/// Decrements the live-stream count when a stream ends.
struct StreamSlot(Arc<AppState>);
impl Drop for StreamSlot {
    fn drop(&mut self) {
        self.0.streams.fetch_sub(1, Ordering::SeqCst);
    }
}

/// `/api/events`: server-sent events, one `snapshot` event (the `/api/monitor` JSON)
/// whenever the journal, the drift references or the manifest change (polled every
/// 250 ms), a comment every 15 s.
async fn events(State(st): State<Arc<AppState>>) -> ApiResult {
    use axum::response::sse::{Event, KeepAlive, Sse};
    if st.kind != SourceKind::Dataset {
        return Err(bad("the monitor needs a dataset directory"));
    }
    if st.streams.fetch_add(1, Ordering::SeqCst) >= MAX_STREAMS {
        st.streams.fetch_sub(1, Ordering::SeqCst);
        return Err(ApiError(
            StatusCode::SERVICE_UNAVAILABLE,
            format!("at most {MAX_STREAMS} live streams"),
        ));
    }
    let slot = StreamSlot(st.clone());
    let mtime = |p: &Path| std::fs::metadata(p).and_then(|m| m.modified()).ok();
    let stream = futures_util::stream::unfold((slot, None), move |(slot, last)| async move {
        loop {
            let root = slot.0.root.clone();
            let key = (
                monitor::journal_len(&root),
                monitor::references_len(&root),
                mtime(&root.join(gonio_dataset::store::MANIFEST_FILE)),
            );
            if last.as_ref() != Some(&key) {
                let snap = tokio::task::spawn_blocking(move || monitor::snapshot(&root)).await;
                let data = match snap {
                    Ok(Ok(s)) => serde_json::to_string(&s).unwrap_or_default(),
                    _ => "{}".to_string(),
                };
                let ev: Result<Event, std::convert::Infallible> = Ok(Event::default().event("snapshot").data(data));
                return Some((ev, (slot, Some(key))));
            }
            tokio::time::sleep(Duration::from_millis(250)).await;
        }
    });
    Ok(Sse::new(stream)
        .keep_alive(KeepAlive::new().interval(Duration::from_secs(15)))
        .into_response())
}

#[cfg(test)]
mod tests {
    use super::*;
    use gonio_btf::compress::testdata::write_test_dataset;
    use gonio_btf::compress::{compress, Method, Params};

    /// `--model` refuses a file of another texture size or other directions and names
    /// what differs; the file compressed from the dataset fits.
    #[test]
    fn a_model_must_match_the_dataset() {
        let grid = |n: usize| -> Vec<[f64; 2]> { (0..n).map(|k| [30.0, 360.0 * k as f64 / n as f64]).collect() };
        let dir = tempfile::tempdir().unwrap();
        let f = |l: usize, v: usize, t: usize, c: usize| 0.1 + 0.01 * ((l + 2 * v + t + c) % 7) as f32;
        let ds = write_test_dataset(&dir.path().join("a"), (4, 4), &grid(5), &grid(4), &[], f);
        let small = write_test_dataset(&dir.path().join("b"), (4, 3), &grid(5), &grid(4), &[], f);
        let fewer = write_test_dataset(&dir.path().join("c"), (4, 4), &grid(6), &grid(4), &[], f);
        let mut moved = grid(4);
        moved[2][1] += 1.0;
        let shifted = write_test_dataset(&dir.path().join("d"), (4, 4), &grid(5), &moved, &[], f);
        let model = |d| CompressedBtf::new(compress(d, &Params::new(Method::Pca, 2)).unwrap().0).unwrap();
        let raw = RawModel::open(&dir.path().join("a")).unwrap();
        assert_eq!(model_mismatch(&raw, &model(&ds)), None);
        let why = model_mismatch(&raw, &model(&small)).unwrap();
        assert!(why.contains("4×3 texels") && why.contains("4×4"), "{why}");
        let why = model_mismatch(&raw, &model(&fewer)).unwrap();
        assert!(why.contains("6 light directions, the dataset 5"), "{why}");
        let why = model_mismatch(&raw, &model(&shifted)).unwrap();
        assert!(why.contains("view 2 is (30.00, 181.00)°"), "{why}");
    }
}
