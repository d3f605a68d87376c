//! The HTTP server: routes onto [`State`], on a Tokio runtime of its own thread.

use std::net::SocketAddr;
use std::sync::atomic::Ordering;
use std::sync::Arc;

use axum::body::Bytes;
use axum::extract::rejection::JsonRejection;
use axum::extract::Request;
use axum::extract::{DefaultBodyLimit, Path, Query, State as Shared};
use axum::http::{header, Method, StatusCode, Uri};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use serde::Deserialize;

use crate::api::{BakeRequest, ErrorBody, JobStarted, StylizeRequest, MAX_URI_BYTES};
use crate::state::{ApiError, State};
use crate::{ViewerConfig, ViewerError};

type AppState = Arc<State>;

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        (self.0, Json(ErrorBody { error: self.1 })).into_response()
    }
}

/// A JSON body, or the 400 that says why it is not one.
fn body<T>(b: Result<Json<T>, JsonRejection>) -> Result<T, ApiError> {
    b.map(|Json(v)| v)
        .map_err(|e| ApiError::bad(format!("the request body: {}", e.body_text())))
}

/// Runs blocking work off the async threads.
async fn blocking<T: Send + 'static>(
    f: impl FnOnce() -> Result<T, ApiError> + Send + 'static,
) -> Result<T, ApiError> {
    tokio::task::spawn_blocking(f)
        .await
        .map_err(|e| ApiError(StatusCode::INTERNAL_SERVER_ERROR, base::error::chain(&e)))?
}

fn bytes(content_type: &'static str, data: Arc<Vec<u8>>) -> Response {
    let body = Bytes::from_owner(ArcBytes(data));
    ([(header::CONTENT_TYPE, content_type)], body).into_response()
}

/// `Arc<Vec<u8>>` as the owner of a response body, without a copy.
struct ArcBytes(Arc<Vec<u8>>);

impl AsRef<[u8]> for ArcBytes {
    fn as_ref(&self) -> &[u8] {
        &self.0
    }
}

async fn index() -> Response {
    asset_response("index.html")
}

fn asset_response(name: &str) -> Response {
    match crate::assets::asset(name) {
        Some((t, c)) => ([(header::CONTENT_TYPE, t)], c).into_response(),
        None => ApiError(StatusCode::NOT_FOUND, format!("no asset `{name}`")).into_response(),
    }
}

async fn asset(Path(name): Path<String>) -> Response {
    asset_response(&name)
}

async fn scene(Shared(s): Shared<AppState>) -> Response {
    Json(s.info()).into_response()
}

async fn gaussians(Shared(s): Shared<AppState>) -> Response {
    bytes("application/octet-stream", s.gaussians.clone())
}

async fn thumbnail(Shared(s): Shared<AppState>, Path(id): Path<String>) -> Response {
    match s.thumbnail(&id) {
        Ok(png) => bytes("image/png", png),
        Err(e) => e.into_response(),
    }
}

#[derive(Deserialize)]
struct UploadQuery {
    name: Option<String>,
}

/// How far past the upload limit a request body is still read (and dropped) before the 413
/// answer: a client that sends the whole body before reading the answer then gets it instead of
/// a broken connection. Longer bodies are cut off.
const UPLOAD_DRAIN_FACTOR: usize = 4;

/// The request body, at most `limit` bytes: `Err` with the status and reason otherwise. A body
/// over the limit is read on, and dropped, up to [`UPLOAD_DRAIN_FACTOR`] times the limit.
async fn read_upload(body: axum::body::Body, limit: usize) -> Result<Vec<u8>, ApiError> {
    use http_body_util::BodyExt;
    let mut body = body;
    let mut data = Vec::new();
    let mut seen = 0usize;
    while let Some(frame) = body.frame().await {
        let frame = frame
            .map_err(|e| ApiError(StatusCode::BAD_REQUEST, format!("reading the upload: {e}")))?;
        let Ok(chunk) = frame.into_data() else {
            continue;
        };
        seen = seen.saturating_add(chunk.len());
        if seen <= limit {
            data.extend_from_slice(&chunk);
        } else if seen > limit.saturating_mul(UPLOAD_DRAIN_FACTOR) {
            break;
        }
    }
    if seen > limit {
        return Err(ApiError(
            StatusCode::PAYLOAD_TOO_LARGE,
            format!(
                "the upload is larger than {} MiB, the upload limit",
                limit >> 20
            ),
        ));
    }
    Ok(data)
}

async fn upload(
    Shared(s): Shared<AppState>,
    Query(q): Query<UploadQuery>,
    body: axum::body::Body,
) -> Response {
    let data = match read_upload(body, s.config.max_upload_bytes).await {
        Ok(d) => d,
        Err(e) => return e.into_response(),
    };
    let name = q.name.unwrap_or_default();
    // The header's pixel count is checked, and the decoding's memory reserved, before any
    // pixel is decoded; decoding then waits for a slot as stylizations do.
    let cost = match s.upload_cost(&name, &data) {
        Ok(c) => c,
        Err(e) => return e.into_response(),
    };
    let _reserved = match s.budget.reserve(cost) {
        Ok(r) => r,
        Err(m) => return ApiError(StatusCode::SERVICE_UNAVAILABLE, m).into_response(),
    };
    let Ok(_slot) = s.stylize_slots.acquire().await else {
        return stopping();
    };
    let state = s.clone();
    match blocking(move || state.upload(&name, &data)).await {
        Ok(info) => (StatusCode::CREATED, Json(info)).into_response(),
        Err(e) => e.into_response(),
    }
}

async fn stylize(
    Shared(s): Shared<AppState>,
    req: Result<Json<StylizeRequest>, JsonRejection>,
) -> Response {
    let req = match body(req) {
        Ok(r) => r,
        Err(e) => return e.into_response(),
    };
    // Checked and costed before any work; the reservation is held while waiting for a slot,
    // so the queue too is bounded by the budget.
    let (camera, cost) = match s.stylize_camera(&req) {
        Ok(c) => c,
        Err(e) => return e.into_response(),
    };
    let _reserved = match s.budget.reserve(cost) {
        Ok(r) => r,
        Err(m) => return ApiError(StatusCode::SERVICE_UNAVAILABLE, m).into_response(),
    };
    // Waiting for a slot holds up no other request.
    let Ok(_slot) = s.stylize_slots.acquire().await else {
        return stopping();
    };
    let state = s.clone();
    match blocking(move || state.stylize(&req, &camera)).await {
        Ok(png) => bytes("image/png", Arc::new(png)),
        Err(e) => e.into_response(),
    }
}

async fn bake(
    Shared(s): Shared<AppState>,
    req: Result<Json<BakeRequest>, JsonRejection>,
) -> Response {
    let req = match body(req) {
        Ok(r) => r,
        Err(e) => return e.into_response(),
    };
    match blocking(move || s.start_bake(&req)).await {
        Ok(job) => (StatusCode::ACCEPTED, Json(JobStarted { job })).into_response(),
        Err(e) => e.into_response(),
    }
}

async fn job(Shared(s): Shared<AppState>, Path(id): Path<String>) -> Response {
    match s.job(&id) {
        Ok(j) => Json(j).into_response(),
        Err(e) => e.into_response(),
    }
}

async fn job_gaussians(Shared(s): Shared<AppState>, Path(id): Path<String>) -> Response {
    match s.job_gaussians(&id) {
        Ok(g) => bytes("application/octet-stream", g),
        Err(e) => e.into_response(),
    }
}

fn stopping() -> Response {
    ApiError(
        StatusCode::SERVICE_UNAVAILABLE,
        "the server is stopping".into(),
    )
    .into_response()
}

async fn not_found() -> Response {
    ApiError(StatusCode::NOT_FOUND, "no such page or API route".into()).into_response()
}

async fn method_not_allowed(method: Method, uri: Uri) -> Response {
    ApiError(
        StatusCode::METHOD_NOT_ALLOWED,
        format!("{method} is not allowed on {}", uri.path()),
    )
    .into_response()
}

/// Longest error text taken over from a response of the HTTP layer into the JSON body.
const MAX_ERROR_TEXT: usize = 4096;

/// Refuses an over-long URI (414) before routing, and gives every error answer that is not
/// already JSON (the framework's own rejections: a body that is not JSON, a bad query or path
/// parameter) the `{"error": ...}` body, with the framework's text as the message.
async fn errors_as_json(request: Request, next: Next) -> Response {
    let uri_len = request
        .uri()
        .path_and_query()
        .map_or(0, |p| p.as_str().len());
    if uri_len > MAX_URI_BYTES {
        let mut answer = ApiError(
            StatusCode::URI_TOO_LONG,
            format!("the request URI is {uri_len} bytes; at most {MAX_URI_BYTES} are accepted"),
        )
        .into_response();
        answer.headers_mut().insert(
            header::CONNECTION,
            header::HeaderValue::from_static("close"),
        );
        return answer;
    }
    let mut response = next.run(request).await;
    // One request a connection, so that every request head passes the connection guard.
    response.headers_mut().insert(
        header::CONNECTION,
        header::HeaderValue::from_static("close"),
    );
    let status = response.status();
    let is_json = response
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|t| t.starts_with("application/json"));
    if !(status.is_client_error() || status.is_server_error()) || is_json {
        return response;
    }
    let (_, body) = response.into_parts();
    let text = match axum::body::to_bytes(body, MAX_ERROR_TEXT).await {
        Ok(b) if !b.is_empty() => String::from_utf8_lossy(&b).trim().to_string(),
        _ => status
            .canonical_reason()
            .unwrap_or("request refused")
            .to_string(),
    };
    let mut answer = ApiError(status, text).into_response();
    answer.headers_mut().insert(
        header::CONNECTION,
        header::HeaderValue::from_static("close"),
    );
    answer
}

fn router(state: AppState) -> Router {
    Router::new()
        .route("/", get(index))
        .route("/assets/{name}", get(asset))
        .route("/api/scene", get(scene))
        .route("/api/gaussians", get(gaussians))
        .route("/api/styles/{id}/thumbnail.png", get(thumbnail))
        .route(
            "/api/styles",
            // The upload reads its own body (`read_upload`), with the limit.
            post(upload).layer(DefaultBodyLimit::disable()),
        )
        .route("/api/stylize", post(stylize))
        .route("/api/bake", post(bake))
        .route("/api/jobs/{id}", get(job))
        .route("/api/jobs/{id}/gaussians", get(job_gaussians))
        .fallback(not_found)
        .method_not_allowed_fallback(method_not_allowed)
        .layer(middleware::from_fn(errors_as_json))
        .with_state(state)
}

/// A running viewer: its address, and the means to stop it.
pub struct Running {
    addr: SocketAddr,
    state: Arc<State>,
    shutdown: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Running {
    /// The address it listens on.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// The page's address, `http://ADDR/`.
    pub fn url(&self) -> String {
        format!("http://{}/", self.addr)
    }

    /// What a program tells its user once the server is up: the scene and the address (the
    /// first line), a warning when the address is reachable from other machines, and how to
    /// stop.
    pub fn banner(&self, scene: &std::path::Path) -> String {
        let mut text = format!("dsgs view: {} at {}\n", scene.display(), self.url());
        if !self.addr.ip().is_loopback() {
            text += &format!(
                "listening on {}: every machine that reaches it can use this viewer\n",
                self.addr
            );
        }
        text + "press Ctrl-C to stop; what the server does is shown below\n"
    }

    /// Blocks until the server ends (it runs until the process is stopped).
    pub fn wait(mut self) {
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }

    /// Stops the server: no new connection is taken, a running bake ends after its current
    /// iteration, and the call returns when the server's thread has ended.
    pub fn stop(mut self) {
        self.halt();
    }

    fn halt(&mut self) {
        self.state.stop.store(true, Ordering::Relaxed);
        if let Some(tx) = self.shutdown.take() {
            let _ = tx.send(());
        }
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for Running {
    fn drop(&mut self) {
        self.halt();
    }
}

/// Reads the scene and the styles of `config`, binds its address and serves on a thread of its
/// own. Returns once the address is bound (port 0 picks a free port: see [`Running::addr`]).
pub fn start(config: ViewerConfig) -> Result<Running, ViewerError> {
    let addr = SocketAddr::new(config.bind, config.port);
    let state = Arc::new(State::load(config)?);
    let io = |what: String| move |error| ViewerError::Io { what, error };
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_io()
        .enable_time()
        .build()
        .map_err(io("starting the server's runtime".into()))?;
    let listener = runtime
        .block_on(tokio::net::TcpListener::bind(addr))
        .map_err(|error| {
            let what = if error.kind() == std::io::ErrorKind::AddrInUse {
                format!(
                    "listening on {addr} (another program, or another dsgs view, has that port: \
                     choose another with --port, or --port 0 for any free one)"
                )
            } else {
                format!("listening on {addr}")
            };
            ViewerError::Io { what, error }
        })?;
    let addr = listener
        .local_addr()
        .map_err(io("reading the bound address".into()))?;
    let (tx, rx) = tokio::sync::oneshot::channel::<()>();
    let app = router(state.clone());
    let thread = std::thread::spawn(move || {
        runtime.block_on(async move {
            let listener = crate::connection::Guarded::new(listener, addr);
            let _ = axum::serve(listener, app)
                .with_graceful_shutdown(async {
                    let _ = rx.await;
                })
                .await;
        });
        // Blocking work still running (a stylization) is not waited for.
        runtime.shutdown_background();
    });
    Ok(Running {
        addr,
        state,
        shutdown: Some(tx),
        thread: Some(thread),
    })
}
