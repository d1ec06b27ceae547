//! The README and the pages under docs/ link to each other and into the repository: every
//! relative link (Markdown `[text](target)` and HTML `src`/`href`) must name a file or folder
//! that exists, an anchor must name a heading of its page (GitHub's anchors), every docs/ page
//! must be reachable from the README, and the README's pictures must be real GIFs.

use std::collections::{BTreeSet, HashMap};
use std::path::{Component, Path, PathBuf};

use junction_tests::workspace_root;

/// The text outside fenced code blocks and inline code, where links are links.
fn prose(markdown: &str) -> String {
    let mut out = String::new();
    let mut fenced = false;
    for line in markdown.lines() {
        if line.trim_start().starts_with("```") {
            fenced = !fenced;
            continue;
        }
        if fenced {
            continue;
        }
        // Inline code spans: drop what is between pairs of backticks.
        for (i, piece) in line.split('`').enumerate() {
            if i % 2 == 0 {
                out.push_str(piece);
            }
        }
        out.push('\n');
    }
    out
}

/// Link targets: `](target)` of Markdown links and images, `src="…"` and `href="…"` of HTML.
fn links(markdown: &str) -> Vec<String> {
    let text = prose(markdown);
    let mut found = Vec::new();
    let mut rest = text.as_str();
    while let Some(start) = rest.find("](") {
        rest = &rest[start + 2..];
        let end = rest.find(')').unwrap_or(rest.len());
        // A title after the target ("…" or '…') is not part of it.
        let target = rest[..end].split_whitespace().next().unwrap_or("");
        found.push(target.to_string());
        rest = &rest[end..];
    }
    for attribute in ["src=\"", "href=\""] {
        let mut rest = text.as_str();
        while let Some(start) = rest.find(attribute) {
            rest = &rest[start + attribute.len()..];
            let end = rest.find('"').unwrap_or(rest.len());
            found.push(rest[..end].to_string());
            rest = &rest[end..];
        }
    }
    found
}

/// GitHub's anchor for a heading: lower case, punctuation dropped (letters, digits, `-` and
/// `_` kept), spaces as `-`; a repeated heading gets `-1`, `-2`, ….
fn anchors(markdown: &str) -> BTreeSet<String> {
    let mut seen: HashMap<String, usize> = HashMap::new();
    let mut out = BTreeSet::new();
    let mut fenced = false;
    for line in markdown.lines() {
        if line.trim_start().starts_with("```") {
            fenced = !fenced;
        }
        let Some(heading) = line.strip_prefix('#').filter(|_| !fenced) else {
            continue;
        };
        let text = heading.trim_start_matches('#').trim();
        let slug: String = text
            .to_lowercase()
            .chars()
            .filter(|c| c.is_alphanumeric() || matches!(c, '-' | '_' | ' '))
            .map(|c| if c == ' ' { '-' } else { c })
            .collect();
        let n = seen.entry(slug.clone()).or_insert(0);
        out.insert(if *n == 0 {
            slug.clone()
        } else {
            format!("{slug}-{n}")
        });
        *n += 1;
    }
    out
}

/// `target` relative to the folder of `from`, with `.` and `..` resolved.
fn resolve(from: &Path, target: &str) -> PathBuf {
    let mut path = from.parent().map(Path::to_path_buf).unwrap_or_default();
    for component in Path::new(target).components() {
        match component {
            Component::ParentDir => {
                path.pop();
            }
            Component::Normal(part) => path.push(part),
            _ => {}
        }
    }
    path
}

fn pages() -> Vec<PathBuf> {
    let root = workspace_root();
    let mut pages = vec![
        root.join("README.md"),
        root.join("deploy/README.md"),
        root.join("fuzz/README.md"),
    ];
    let mut docs: Vec<PathBuf> = std::fs::read_dir(root.join("docs"))
        .expect("docs/")
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|e| e == "md"))
        .collect();
    docs.sort();
    pages.extend(docs);
    pages
}

#[test]
fn every_link_of_the_readme_and_the_docs_resolves() {
    let mut broken = Vec::new();
    let mut checked = 0;
    let mut linked: BTreeSet<PathBuf> = BTreeSet::new();
    for page in pages() {
        let text =
            std::fs::read_to_string(&page).unwrap_or_else(|e| panic!("{}: {e}", page.display()));
        for target in links(&text) {
            if target.contains("://") || target.starts_with("mailto:") {
                continue;
            }
            checked += 1;
            let (path, anchor) = match target.split_once('#') {
                Some((path, anchor)) => (path, Some(anchor)),
                None => (target.as_str(), None),
            };
            let file = if path.is_empty() {
                page.clone()
            } else {
                resolve(&page, path)
            };
            if !file.exists() {
                broken.push(format!("{}: {target} (no such file)", page.display()));
                continue;
            }
            linked.insert(file.clone());
            if let Some(anchor) = anchor {
                let headings = anchors(&std::fs::read_to_string(&file).unwrap_or_default());
                if !headings.contains(anchor) {
                    broken.push(format!(
                        "{}: {target} (no heading #{anchor} in {}; it has {headings:?})",
                        page.display(),
                        file.display()
                    ));
                }
            }
        }
    }
    assert!(broken.is_empty(), "broken links:\n{}", broken.join("\n"));
    assert!(
        checked > 40,
        "only {checked} relative links found: is the parser broken?"
    );

    // Every page under docs/ is linked from the README or from a page it links to.
    let orphans: Vec<String> = pages()
        .into_iter()
        .filter(|p| p.starts_with(workspace_root().join("docs")) && !linked.contains(p))
        .map(|p| p.display().to_string())
        .collect();
    assert!(
        orphans.is_empty(),
        "docs pages nothing links to: {orphans:?}"
    );
}

#[test]
fn the_readme_pictures_are_gifs_in_the_repository() {
    let readme_path = workspace_root().join("README.md");
    let readme = std::fs::read_to_string(&readme_path).expect("README.md");
    let pictures: Vec<String> = links(&readme)
        .into_iter()
        .filter(|t| t.ends_with(".gif"))
        .collect();
    assert!(
        pictures.len() >= 2,
        "the README shows the intersection and the roundabout: {pictures:?}"
    );
    for picture in pictures {
        let bytes = std::fs::read(resolve(&readme_path, &picture))
            .unwrap_or_else(|e| panic!("{picture}: {e}"));
        assert_eq!(&bytes[..6], b"GIF89a", "{picture} is not a GIF");
        assert!(
            bytes.len() < 3_000_000,
            "{picture}: {} bytes, keep it small",
            bytes.len()
        );
    }
}

#[test]
fn the_link_parser_finds_links_and_anchors_as_github_makes_them() {
    let text = "See [a](docs/A.md#the-x), ![p](m.gif \"title\") and <img src=\"b.gif\">.\n\
                `[not](a-link)`\n```\n[nor](this)\n```\n";
    assert_eq!(links(text), ["docs/A.md#the-x", "m.gif", "b.gif"]);
    let headings =
        anchors("# Junction\n## Training curves: `progress.jsonl`\n## Faults\n## Faults\n");
    let expected = [
        "faults",
        "faults-1",
        "junction",
        "training-curves-progressjsonl",
    ];
    assert_eq!(headings, expected.iter().map(|s| s.to_string()).collect());
    assert_eq!(
        resolve(Path::new("/r/docs/A.md"), "../README.md"),
        Path::new("/r/README.md")
    );
}
