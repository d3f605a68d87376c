//! The HTTP server: routes onto [`State`], on a Tokio runtime of its own thread.

use std::net::SocketAddr;
use std::sync::atomic::Ordering;
use std::sync::Arc;

use axum::body::Bytes;
use axum::extract::rejection::JsonRejection;
use axum::extract::{DefaultBodyLimit, Path, Query, State as Shared};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use serde::Deserialize;

use crate::api::{BakeRequest, ErrorBody, JobStarted, StylizeRequest};
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
        .map_err(|e| ApiError(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?
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
    match blocking(move || s.upload(&name, &data)).await {
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
    // Waiting for a slot holds up no other request.
    let Ok(_slot) = s.stylize_slots.acquire().await else {
        return ApiError(
            StatusCode::SERVICE_UNAVAILABLE,
            "the server is stopping".into(),
        )
        .into_response();
    };
    let state = s.clone();
    match blocking(move || state.stylize(&req)).await {
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

async fn not_found() -> Response {
    ApiError(StatusCode::NOT_FOUND, "no such page or API route".into()).into_response()
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
        .map_err(io(format!("listening on {addr}")))?;
    let addr = listener
        .local_addr()
        .map_err(io("reading the bound address".into()))?;
    let (tx, rx) = tokio::sync::oneshot::channel::<()>();
    let app = router(state.clone());
    let thread = std::thread::spawn(move || {
        runtime.block_on(async move {
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
