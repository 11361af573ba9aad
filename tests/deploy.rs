//! The deploy files say only what the binary understands: every `sylva` invocation in
//! deploy/Dockerfile, deploy/compose.yaml and deploy/k8s/ names a real subcommand and real
//! flags, every `SYLVA_*` variable they (and deploy/README.md) set is one the CLI reads, the
//! YAML parses, and the health checks and probes point at routes the API serves, on the port
//! it listens on. The CLI is read through clap (the binary's `cli::Cli`), not by running the
//! binary.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use clap::CommandFactory;
use serde_norway::Value;

// The command line is the binary's (src/main.rs), not the library's: its two modules are
// compiled into this test as they are into the binary, so that clap's definition of every
// subcommand, flag and variable can be read here. Only `Cli` is used.
#[allow(dead_code, unused_imports)]
#[path = "../src/cli/mod.rs"]
mod cli;
#[allow(dead_code, unused_imports)]
#[path = "../src/loadbench/mod.rs"]
mod loadbench;

fn deploy_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy")
}

fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// Long flags and environment variables of one subcommand.
#[derive(Default)]
struct Surface {
    flags: BTreeSet<String>,
    envs: BTreeSet<String>,
}

/// Every subcommand's flags and variables, by subcommand name.
fn cli() -> BTreeMap<String, Surface> {
    let mut cmd = cli::Cli::command();
    // Built, so that clap's own --help and --version are listed too.
    cmd.build();
    cmd.get_subcommands()
        .map(|sub| {
            let mut s = Surface::default();
            for a in sub.get_arguments() {
                if let Some(long) = a.get_long() {
                    s.flags.insert(format!("--{long}"));
                }
                if let Some(env) = a.get_env() {
                    s.envs.insert(env.to_string_lossy().into_owned());
                }
            }
            (sub.get_name().to_string(), s)
        })
        .collect()
}

/// `SYLVA_*` names read by any of `subs` (all subcommands when empty).
fn envs_of(cli: &BTreeMap<String, Surface>, subs: &[&str]) -> BTreeSet<String> {
    cli.iter()
        .filter(|(name, _)| subs.is_empty() || subs.contains(&name.as_str()))
        .flat_map(|(_, s)| s.envs.iter().cloned())
        .collect()
}

/// Checks `sylva ARGS…`; returns the subcommand.
fn check_invocation(
    cli: &BTreeMap<String, Surface>,
    args: &[String],
    at: &str,
    errors: &mut Vec<String>,
) -> Option<String> {
    let Some(sub) = args.first() else {
        errors.push(format!("{at}: no subcommand"));
        return None;
    };
    let Some(surface) = cli.get(sub) else {
        errors.push(format!("{at}: `sylva {sub}` is not a subcommand"));
        return None;
    };
    for arg in &args[1..] {
        // `--name`, `--name=value`, or in prose `--name`).` and the like.
        if let Some(rest) = arg.strip_prefix("--") {
            let name: String = rest
                .chars()
                .take_while(|c| c.is_ascii_alphanumeric() || *c == '-')
                .collect();
            let flag = format!("--{name}");
            if !surface.flags.contains(&flag) {
                errors.push(format!("{at}: `sylva {sub}` has no flag {flag}"));
            }
        }
    }
    Some(sub.clone())
}

fn check_env_name(envs: &BTreeSet<String>, name: &str, at: &str, errors: &mut Vec<String>) {
    if name.starts_with("SYLVA_") && !envs.contains(name) {
        errors.push(format!("{at}: {name} is read by no subcommand here"));
    }
}

/// Every `SYLVA_[A-Z0-9_]+` in `text`.
fn sylva_vars(text: &str) -> BTreeSet<String> {
    let mut out = BTreeSet::new();
    let mut rest = text;
    while let Some(i) = rest.find("SYLVA_") {
        let tail = &rest[i..];
        let end = tail
            .find(|c: char| !(c.is_ascii_uppercase() || c.is_ascii_digit() || c == '_'))
            .unwrap_or(tail.len());
        out.insert(tail[..end].trim_end_matches('_').to_string());
        rest = &tail[end..];
    }
    out
}

/// True when `(GET, path)` is routed.
fn is_get_route(path: &str) -> bool {
    sylva::api::ROUTES.contains(&("GET", path))
}

/// `(port, path)` of the first `http://host:port/path` in `text`.
fn http_url(text: &str) -> Option<(u16, String)> {
    let start = text.find("http://")? + "http://".len();
    let rest = &text[start..];
    let end = rest
        .find(|c: char| c.is_whitespace() || c == '"')
        .unwrap_or(rest.len());
    let url = &rest[..end];
    let (authority, path) = url.split_at(url.find('/')?);
    let port = authority.rsplit(':').next()?.parse().ok()?;
    Some((port, path.to_string()))
}

fn port_of(listen: &str) -> Option<u16> {
    listen.rsplit(':').next()?.parse().ok()
}

/// The subcommand that a container's arguments run (without any, the image's CMD: `serve`),
/// checked as [`check_invocation`] does, and the environment variables it reads.
fn invocation(
    cli: &BTreeMap<String, Surface>,
    args: Option<&Value>,
    at: &str,
    errors: &mut Vec<String>,
) -> Option<(String, BTreeSet<String>)> {
    let args = args.map(strings).unwrap_or_else(|| vec!["serve".into()]);
    let sub = check_invocation(cli, &args, at, errors)?;
    let envs = envs_of(cli, &[sub.as_str()]);
    Some((sub, envs))
}

fn strings(v: &Value) -> Vec<String> {
    match v {
        Value::Sequence(items) => items
            .iter()
            .filter_map(|i| match i {
                Value::String(s) => Some(s.clone()),
                Value::Number(n) => Some(n.to_string()),
                _ => None,
            })
            .collect(),
        Value::String(s) => s.split_whitespace().map(str::to_string).collect(),
        _ => Vec::new(),
    }
}

fn parse_yaml_docs(path: &Path) -> Vec<Value> {
    let text = read(path);
    serde_norway::Deserializer::from_str(&text)
        .map(|doc| {
            let mut v = <Value as serde::Deserialize>::deserialize(doc)
                .unwrap_or_else(|e| panic!("{} does not parse: {e}", path.display()));
            v.apply_merge()
                .unwrap_or_else(|e| panic!("{}: merge keys: {e}", path.display()));
            v
        })
        .collect()
}

/// The Dockerfile's instructions: comment lines dropped, continuation lines joined.
fn dockerfile_instructions(text: &str) -> Vec<(String, String)> {
    let mut out = Vec::new();
    let mut current = String::new();
    for line in text.lines() {
        let trimmed = line.trim();
        if trimmed.starts_with('#') || (trimmed.is_empty() && current.is_empty()) {
            continue;
        }
        match trimmed.strip_suffix('\\') {
            Some(head) => {
                current.push_str(head);
                current.push(' ');
            }
            None => {
                current.push_str(trimmed);
                let (word, rest) = current.split_once(' ').unwrap_or((&current, ""));
                out.push((word.to_ascii_uppercase(), rest.trim().to_string()));
                current.clear();
            }
        }
    }
    out
}

#[test]
fn dockerfile_runs_real_commands_and_checks_a_real_route() {
    let cli = cli();
    let all_envs = envs_of(&cli, &[]);
    let text = read(&deploy_dir().join("Dockerfile"));
    let mut errors = Vec::new();
    let mut listen_port = None;
    let mut health = None;
    let mut entrypoint = None;
    let mut cmd = None;
    for (word, rest) in dockerfile_instructions(&text) {
        match word.as_str() {
            "ENV" => {
                for pair in rest.split_whitespace() {
                    let (k, v) = pair.split_once('=').unwrap_or((pair, ""));
                    check_env_name(&all_envs, k, "Dockerfile ENV", &mut errors);
                    if k == "SYLVA_LISTEN" {
                        listen_port = port_of(v);
                    }
                }
            }
            "HEALTHCHECK" => health = http_url(&rest),
            "ENTRYPOINT" => entrypoint = serde_json::from_str::<Vec<String>>(&rest).ok(),
            "CMD" => cmd = serde_json::from_str::<Vec<String>>(&rest).ok(),
            _ => {}
        }
    }
    let entrypoint = entrypoint.expect("ENTRYPOINT in exec (JSON) form");
    assert!(
        entrypoint.len() == 1 && entrypoint[0].ends_with("/sylva"),
        "ENTRYPOINT should be the sylva binary alone: {entrypoint:?}"
    );
    let cmd = cmd.expect("CMD in exec (JSON) form");
    check_invocation(&cli, &cmd, "Dockerfile CMD", &mut errors);
    let (port, path) = health.expect("a HEALTHCHECK with an http:// URL");
    assert!(is_get_route(&path), "HEALTHCHECK {path} is not a GET route");
    assert_eq!(
        Some(port),
        listen_port,
        "HEALTHCHECK port against SYLVA_LISTEN"
    );
    assert!(errors.is_empty(), "{errors:#?}");
}

#[test]
fn compose_file_parses_and_uses_real_flags_and_variables() {
    let cli = cli();
    let docs = parse_yaml_docs(&deploy_dir().join("compose.yaml"));
    assert_eq!(docs.len(), 1, "compose.yaml is one document");
    let services = docs[0]
        .get("services")
        .and_then(Value::as_mapping)
        .expect("services:");
    let mut errors = Vec::new();
    let mut sylva_subs = BTreeSet::new();
    for (name, svc) in services {
        let name = name.as_str().unwrap_or("?");
        let image = svc.get("image").and_then(Value::as_str).unwrap_or("");
        let is_sylva = svc.get("build").is_some() || image.starts_with("sylva");
        if !is_sylva {
            continue;
        }
        let at = format!("compose service {name}");
        let Some((sub, envs)) = invocation(&cli, svc.get("command"), &at, &mut errors) else {
            continue;
        };
        let env = svc
            .get("environment")
            .and_then(Value::as_mapping)
            .expect("environment as a mapping");
        for (k, v) in env {
            let k = k.as_str().unwrap_or("");
            check_env_name(&envs, k, &at, &mut errors);
            if k == "SYLVA_LISTEN" {
                let port = v
                    .as_str()
                    .and_then(port_of)
                    .expect("SYLVA_LISTEN host:port");
                let ports = svc.get("ports").map(strings).unwrap_or_default();
                assert!(
                    ports.iter().all(|p| p.ends_with(&format!(":{port}"))),
                    "{at}: published ports {ports:?} against SYLVA_LISTEN port {port}"
                );
            }
        }
        if let Some(hc) = svc.get("healthcheck")
            && let Some((_, path)) =
                http_url(&strings(hc.get("test").unwrap_or(&Value::Null)).join(" "))
        {
            assert!(
                is_get_route(&path),
                "{at}: healthcheck {path} is not a GET route"
            );
        }
        sylva_subs.insert(sub);
    }
    assert!(
        sylva_subs.contains("serve") && sylva_subs.contains("worker"),
        "compose runs both `sylva serve` and `sylva worker`: {sylva_subs:?}"
    );
    assert!(errors.is_empty(), "{errors:#?}");
}

#[test]
fn kubernetes_manifests_parse_and_probe_real_routes() {
    let cli = cli();
    let shared_envs = envs_of(&cli, &["serve", "worker"]);
    let dir = deploy_dir().join("k8s");
    let mut errors = Vec::new();
    let mut files: BTreeSet<String> = BTreeSet::new();
    let mut listen_port = None;
    let mut containers = Vec::new();
    let mut probes = 0;
    for entry in std::fs::read_dir(&dir).expect("deploy/k8s") {
        let path = entry.expect("dir entry").path();
        if path.extension().and_then(|e| e.to_str()) != Some("yaml") {
            continue;
        }
        let file = path
            .file_name()
            .and_then(|n| n.to_str())
            .unwrap_or("?")
            .to_string();
        for doc in parse_yaml_docs(&path) {
            match doc.get("kind").and_then(Value::as_str) {
                Some("ConfigMap") | Some("Secret") => {
                    for key in ["data", "stringData"] {
                        for (k, v) in doc
                            .get(key)
                            .and_then(Value::as_mapping)
                            .into_iter()
                            .flatten()
                        {
                            let k = k.as_str().unwrap_or("");
                            check_env_name(&shared_envs, k, &file, &mut errors);
                            if k == "SYLVA_LISTEN" {
                                listen_port = v.as_str().and_then(port_of);
                            }
                        }
                    }
                }
                Some("Deployment") => {
                    let spec = &doc["spec"]["template"]["spec"]["containers"];
                    for c in spec.as_sequence().into_iter().flatten() {
                        containers.push((file.clone(), c.clone()));
                    }
                }
                _ => {}
            }
        }
        files.insert(file);
    }
    for (file, c) in &containers {
        let image = c.get("image").and_then(Value::as_str).unwrap_or("");
        if !image.starts_with("sylva") {
            continue;
        }
        let at = format!("{file} container {}", c["name"].as_str().unwrap_or("?"));
        let Some((sub, envs)) = invocation(&cli, c.get("args"), &at, &mut errors) else {
            continue;
        };
        for e in c
            .get("env")
            .and_then(Value::as_sequence)
            .into_iter()
            .flatten()
        {
            check_env_name(&envs, e["name"].as_str().unwrap_or(""), &at, &mut errors);
        }
        let ports: BTreeMap<String, u64> = c
            .get("ports")
            .and_then(Value::as_sequence)
            .into_iter()
            .flatten()
            .filter_map(|p| {
                Some((
                    p["name"].as_str()?.to_string(),
                    p["containerPort"].as_u64()?,
                ))
            })
            .collect();
        for probe in ["startupProbe", "livenessProbe", "readinessProbe"] {
            let Some(get) = c.get(probe).and_then(|p| p.get("httpGet")) else {
                continue;
            };
            probes += 1;
            let path = get["path"].as_str().unwrap_or("");
            assert!(
                is_get_route(path),
                "{at}: {probe} {path} is not a GET route"
            );
            let port = match &get["port"] {
                Value::String(name) => ports.get(name).copied(),
                other => other.as_u64(),
            };
            assert_eq!(
                port,
                listen_port.map(u64::from),
                "{at}: {probe} port against SYLVA_LISTEN in the ConfigMap"
            );
        }
        if sub == "serve" {
            for probe in ["livenessProbe", "readinessProbe"] {
                assert!(c.get(probe).is_some(), "{at}: no {probe}");
            }
        }
    }
    assert!(probes >= 2, "the API has liveness and readiness probes");
    // kustomization.yaml lists every manifest, and only files that exist.
    let kustomization = parse_yaml_docs(&dir.join("kustomization.yaml"));
    let listed: BTreeSet<String> = kustomization[0]
        .get("resources")
        .map(strings)
        .unwrap_or_default()
        .into_iter()
        .collect();
    let manifests: BTreeSet<String> = files
        .into_iter()
        .filter(|f| f != "kustomization.yaml")
        .collect();
    assert_eq!(
        listed, manifests,
        "kustomization.yaml resources against deploy/k8s/*.yaml"
    );
    assert!(errors.is_empty(), "{errors:#?}");
}

#[test]
fn deploy_texts_name_only_real_variables_and_flags() {
    let cli = cli();
    let all_envs = envs_of(&cli, &[]);
    let mut errors = Vec::new();
    let mut texts = vec![
        deploy_dir().join("Dockerfile"),
        deploy_dir().join("compose.yaml"),
    ];
    texts.push(deploy_dir().join("README.md"));
    for entry in std::fs::read_dir(deploy_dir().join("k8s")).expect("deploy/k8s") {
        texts.push(entry.expect("dir entry").path());
    }
    for path in &texts {
        let text = read(path);
        let at = path.display().to_string();
        // Comments and prose too: a variable named anywhere must exist.
        for var in sylva_vars(&text) {
            check_env_name(&all_envs, &var, &at, &mut errors);
        }
        // Command lines: `sylva SUB --flag …` in the README's examples.
        for line in text.lines() {
            let words: Vec<&str> = line.split_whitespace().collect();
            for (i, w) in words.iter().enumerate() {
                let w = w.trim_matches('`');
                if w != "sylva" && !w.ends_with("/sylva") {
                    continue;
                }
                let Some(sub) = words.get(i + 1).map(|s| s.trim_matches('`')) else {
                    continue;
                };
                if !cli.contains_key(sub) {
                    continue;
                }
                let args: Vec<String> = words[i + 1..]
                    .iter()
                    .take_while(|w| !matches!(**w, "|" | "&&" | ";" | "#"))
                    .map(|w| {
                        w.trim_matches(|c| c == '`' || c == '\'' || c == '"')
                            .to_string()
                    })
                    .collect();
                check_invocation(&cli, &args, &at, &mut errors);
            }
        }
    }
    assert!(errors.is_empty(), "{errors:#?}");
}
