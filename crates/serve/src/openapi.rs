//! The route table ([`ROUTES`]) the router is built from, and the OpenAPI document
//! ([`openapi`]) generated from the same table, so the two cannot drift apart (a test
//! also calls every documented route over HTTP).

use crate::inputs::all_parts;
use serde_json::json;

/// One route of the API.
#[derive(Debug, Clone, Copy)]
pub struct Route {
    /// HTTP method (`GET`).
    pub method: &'static str,
    /// Path in OpenAPI form (`/v1/jobs/{id}`); `{path}` is the rest of the URL.
    pub path: &'static str,
    /// What it does.
    pub summary: &'static str,
    /// Whether it answers without a token.
    pub open: bool,
}

/// Every route the server has.
pub const ROUTES: &[Route] = &[
    Route { method: "GET", path: "/health", summary: "Alive (no token needed).", open: true },
    Route { method: "GET", path: "/ready", summary: "Model loaded and queue not full: 200, else 503.", open: false },
    Route { method: "GET", path: "/metrics", summary: "Prometheus text: queue depth, jobs by status, stage-seconds histograms, memory.", open: false },
    Route { method: "GET", path: "/openapi.json", summary: "This document.", open: false },
    Route {
        method: "POST",
        path: "/v1/reconstruct",
        summary: "RGB-D frame (or two) + masks → per object pose, mesh and Gaussians (recon infer). wait=true (default) answers when done; wait=false answers 202 with the job.",
        open: false,
    },
    Route { method: "GET", path: "/v1/jobs/{id}", summary: "A job: status, stage, progress, and the result when done.", open: false },
    Route {
        method: "DELETE",
        path: "/v1/jobs/{id}",
        summary: "Cancels a queued or running job (a running one stops at its next stage boundary); deletes a finished one.",
        open: false,
    },
    Route { method: "GET", path: "/v1/jobs/{id}/files/{path}", summary: "A file recon infer wrote for the job, byte for byte.", open: false },
    Route { method: "GET", path: "/v1/jobs/{id}/archive", summary: "Every file of the job's output as one zip.", open: false },
    Route {
        method: "POST",
        path: "/v1/jobs/{id}/scene",
        summary: "recon scene on a finished job (collision, settling, URDF/MJCF/USD); body: recon scene's options as JSON.",
        open: false,
    },
    Route { method: "GET", path: "/v1/jobs/{id}/scene/files/{path}", summary: "A file recon scene wrote for the job.", open: false },
];

/// The route's path in axum's syntax (`{path}` → `{*path}`).
pub fn axum_path(path: &str) -> String {
    path.replace("{path}", "{*path}")
}

/// The OpenAPI 3.0 document of [`ROUTES`].
pub fn openapi() -> serde_json::Value {
    let mut paths = serde_json::Map::new();
    for r in ROUTES {
        let mut params = Vec::new();
        for name in ["id", "path"] {
            if r.path.contains(&format!("{{{name}}}")) {
                params.push(json!({"name": name, "in": "path", "required": true, "schema": {"type": "string"},
                    "description": if name == "id" { "job id (32 hex digits)" } else { "file path inside the output folder" }}));
            }
        }
        if r.path == "/v1/reconstruct" {
            params.push(json!({"name": "wait", "in": "query", "required": false, "schema": {"type": "boolean", "default": true}}));
        }
        let mut op = json!({
            "summary": r.summary,
            "operationId": format!("{}{}", r.method.to_lowercase(), r.path.replace(['/', '{', '}', '.'], "_")),
            "parameters": params,
            "responses": responses(r),
        });
        if r.open {
            op["security"] = json!([]);
        }
        if r.path == "/v1/reconstruct" {
            let parts = all_parts();
            let props: serde_json::Map<String, serde_json::Value> = parts
                .iter()
                .map(|(name, _, what)| {
                    let binary = !crate::inputs::is_small_part(name);
                    let schema = if binary {
                        json!({"type": "string", "format": "binary", "description": what})
                    } else {
                        json!({"type": "string", "description": what})
                    };
                    let schema = if crate::inputs::is_repeatable(name) {
                        json!({"type": "array", "items": schema, "description": what})
                    } else {
                        schema
                    };
                    (name.to_string(), schema)
                })
                .collect();
            let required: Vec<&str> = parts.iter().filter(|p| p.1).map(|p| p.0.as_str()).collect();
            op["requestBody"] = json!({"required": true, "content": {"multipart/form-data": {"schema": {"type": "object", "properties": props, "required": required}}}});
        }
        if r.path == "/v1/jobs/{id}/scene" {
            op["requestBody"] = json!({"required": false, "content": {"application/json": {"schema": {"type": "object",
                "description": "recon scene's options by name (docs/options.md); absent ones take their defaults"}}}});
        }
        let entry = paths.entry(r.path.to_string()).or_insert_with(|| json!({}));
        entry[r.method.to_lowercase()] = op;
    }
    json!({
        "openapi": "3.0.3",
        "info": {"title": "recon serve", "version": "1", "description": "RGB-D frames + object masks → metric poses, meshes, Gaussians and sim-ready scenes (docs/serve.md)."},
        "paths": paths,
        "components": {
            "securitySchemes": {"bearer": {"type": "http", "scheme": "bearer"}},
            "schemas": {"Error": {"type": "object", "properties": {"error": {"type": "object", "properties": {
                "status": {"type": "integer"}, "part": {"type": "string", "nullable": true},
                "field": {"type": "string", "nullable": true}, "message": {"type": "string"}}}}}},
        },
        "security": [{"bearer": []}],
    })
}

fn responses(r: &Route) -> serde_json::Value {
    let err = |d: &str| json!({"description": d, "content": {"application/json": {"schema": {"$ref": "#/components/schemas/Error"}}}});
    let mut m = serde_json::Map::new();
    m.insert("200".into(), json!({"description": "OK"}));
    if !r.open {
        m.insert("401".into(), err("missing or wrong bearer token"));
    }
    match (r.method, r.path) {
        ("POST", "/v1/reconstruct") => {
            m.insert("202".into(), json!({"description": "wait=false: the job, queued"}));
            m.insert("400".into(), err("a part or field is missing or wrong (named)"));
            m.insert("409".into(), err("wait=true: the job was cancelled"));
            m.insert("413".into(), err("upload or image over a limit"));
            m.insert("422".into(), err("wait=true: the job failed on its input"));
            m.insert("429".into(), err("queue full; Retry-After says when to try again"));
            m.insert("503".into(), err("shutting down, or the job failed on the server's side"));
            m.insert("504".into(), err("wait=true: the job ran past --job-timeout-s"));
        }
        (_, p) if p.starts_with("/v1/jobs/") => {
            m.insert("404".into(), err("no such job or file"));
            m.insert("409".into(), err("the job is not done"));
        }
        ("GET", "/ready") => {
            m.insert("503".into(), err("not ready (queue full or shutting down)"));
        }
        _ => {}
    }
    serde_json::Value::Object(m)
}
