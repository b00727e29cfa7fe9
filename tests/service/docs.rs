//! The documentation says what the code does: openapi.yaml states the preview pool and size
//! limit, octet-stream uploads and ranged downloads; the README links the reference, which
//! covers every parameter and route. Regression tests from tests/edges.rs (issue 25's sharp edges).

/// openapi.yaml says what the server does: previews on their own pool, preview `size` at most
/// 4096, octet-stream uploads, ranged downloads.
#[test]
fn openapi_states_pools_sizes_uploads_and_ranges() {
    let doc: serde_yaml_ng::Value =
        serde_yaml_ng::from_str(horizon_bake::service::handlers::OPENAPI_YAML).unwrap();
    let paths = &doc["paths"];
    let preview = &paths["/v1/bakes/{id}/preview"]["get"];
    let desc = preview["description"].as_str().unwrap();
    assert!(!desc.contains("bake pool.") && desc.contains("preview pool"), "{desc}");
    let size =
        preview["parameters"].as_sequence().unwrap().iter().find(|p| p["name"] == "size").unwrap();
    assert!(size["description"].as_str().unwrap().contains("4096"), "{size:?}");
    assert_eq!(horizon_bake::preview::MAX_SIZE, 4096);
    let body = &paths["/v1/bakes"]["post"]["requestBody"]["content"];
    assert!(!body["application/octet-stream"].is_null());
    for p in ["/v1/bakes/{id}/horizon/{layer}", "/v1/bakes/{id}/horizon.ktx2"] {
        let r = &paths[p]["get"]["responses"];
        assert!(!r["206"].is_null() && !r["416"].is_null(), "{p}");
    }
}

/// The README links the reference in the repository (a clone has no ../shared), and the
/// reference covers every bake parameter, every preview parameter and every route.
#[test]
fn readme_links_the_reference_which_covers_every_parameter_and_route() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let readme = std::fs::read_to_string(root.join("README.md")).unwrap();
    assert!(readme.contains("(docs/reference.md)"), "README does not link docs/reference.md");
    let mut docs = vec![("README.md".to_owned(), readme)];
    for e in std::fs::read_dir(root.join("docs")).unwrap().flatten() {
        if e.path().extension().is_some_and(|x| x == "md") {
            docs.push((e.path().display().to_string(), std::fs::read_to_string(e.path()).unwrap()));
        }
    }
    for (name, text) in &docs {
        assert!(!text.contains("../shared") && !text.contains("shared/SPEC"), "{name}");
    }
    let reference = std::fs::read_to_string(root.join("docs/reference.md")).unwrap();
    let names = horizon_bake::params::PARAM_NAMES
        .iter()
        .chain(horizon_bake::preview::PREVIEW_PARAM_NAMES)
        .chain(&["formats", "exr_precision"])
        .chain(&horizon_bake::encode::texture::OPTION_KEYS);
    for k in names {
        assert!(reference.contains(&format!("`{k}`")), "docs/reference.md lacks `{k}`");
    }
    for (route, _) in horizon_bake::service::ROUTES {
        assert!(reference.contains(&format!("`{route}`")), "docs/reference.md lacks {route}");
    }
    for topic in ["height_scale", "y_axis", "edge=wrap", "encoding=sqrt", "+X, −X", "hardness"] {
        assert!(reference.contains(topic), "docs/reference.md lacks {topic}");
    }
}
