//! The web page: one HTML file, its stylesheet and three scripts, compiled into the binary so
//! the service needs nothing at run time and the browser fetches nothing from elsewhere.
//!
//! The page is plain HTML/CSS/JavaScript (no framework, no build step): `app.js` holds the
//! jobs list, the upload form and the job page; `viewer.js` the WebGL2 Gaussian-splat viewer;
//! `tiles.js` the streamer that feeds it a job's 3D Tiles tileset by level of detail.
//! A strict Content-Security-Policy keeps every script, style and connection on this origin.

use axum::extract::Path;
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};

use super::problem::ApiError;

/// One embedded file: its name under `/assets/`, content type and bytes.
struct Asset {
    name: &'static str,
    content_type: &'static str,
    body: &'static str,
}

const ASSETS: &[Asset] = &[
    Asset {
        name: "app.css",
        content_type: "text/css; charset=utf-8",
        body: include_str!("web/app.css"),
    },
    Asset {
        name: "app.js",
        content_type: "text/javascript; charset=utf-8",
        body: include_str!("web/app.js"),
    },
    Asset {
        name: "viewer.js",
        content_type: "text/javascript; charset=utf-8",
        body: include_str!("web/viewer.js"),
    },
    Asset {
        name: "tiles.js",
        content_type: "text/javascript; charset=utf-8",
        body: include_str!("web/tiles.js"),
    },
];

const INDEX_HTML: &str = include_str!("web/index.html");

/// Everything the page loads comes from this origin; images may also be blob URLs (artifacts
/// fetched with the bearer token) and data URLs (the favicon).
const CSP: &str = "default-src 'self'; img-src 'self' blob: data:; style-src 'self'; \
                   script-src 'self'; connect-src 'self'; object-src 'none'; \
                   base-uri 'none'; frame-ancestors 'none'";

fn page(content_type: &'static str, body: &'static str) -> Response {
    let mut resp = body.into_response();
    let h = resp.headers_mut();
    h.insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
    // The binary is the version: revalidate so an upgraded server is never mixed with a
    // cached older script.
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    h.insert(
        header::CONTENT_SECURITY_POLICY,
        HeaderValue::from_static(CSP),
    );
    h.insert(
        header::X_CONTENT_TYPE_OPTIONS,
        HeaderValue::from_static("nosniff"),
    );
    resp
}

/// `GET /`: the single-page interface.
pub async fn index() -> Response {
    page("text/html; charset=utf-8", INDEX_HTML)
}

/// `GET /assets/{name}`: the page's stylesheet and scripts.
pub async fn asset(Path(name): Path<String>) -> Response {
    match ASSETS.iter().find(|a| a.name == name) {
        Some(a) => page(a.content_type, a.body),
        None => ApiError::new(
            StatusCode::NOT_FOUND,
            "no-such-asset",
            format!("the page has no asset {name:?}"),
        )
        .into_response(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_page_links_every_asset_and_nothing_from_elsewhere() {
        for a in ASSETS {
            assert!(
                INDEX_HTML.contains(&format!("/assets/{}", a.name)),
                "index.html does not load {}",
                a.name
            );
        }
        // The SVG namespace is a name, not a fetch; anything else absolute would be one.
        for text in std::iter::once(INDEX_HTML).chain(ASSETS.iter().map(|a| a.body)) {
            let text = text.replace("http://www.w3.org/2000/svg", "");
            assert!(!text.contains("http://") && !text.contains("https://"));
        }
    }
}
