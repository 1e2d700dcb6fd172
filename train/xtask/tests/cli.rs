//! `g2r-xtask results-page` as a user runs it: it writes the pages and the README's block, and `--check` fails,
//! naming the file and the command that fixes it, when one was edited by hand.

use std::process::Command;

fn xtask(args: &[&str]) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_g2r-xtask"))
        .args(args)
        .output()
        .unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

fn error_line(stderr: &str) -> &str {
    stderr
        .lines()
        .find(|l| l.starts_with("error"))
        .unwrap_or("")
}

#[test]
fn results_page_writes_the_page_and_check_fails_when_it_differs() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::create_dir(d.join("records")).unwrap();
    std::fs::write(
        d.join("records/10-a.json"),
        "{\"title\": \"A\", \"columns\": [\"what\"], \"rows\": [\n{\"id\": \"10.1\", \"cells\": [\"x\"]}]}",
    )
    .unwrap();
    let readme_block = "<!-- generated: results-page 10-a.json -->\n<!-- end generated -->\n";
    std::fs::write(d.join("README.md"), readme_block).unwrap();
    let records = d.join("records").to_string_lossy().into_owned();
    let page = d.join("results.md").to_string_lossy().into_owned();
    let archive = d.join("results-archive.md").to_string_lossy().into_owned();
    let readme = d.join("README.md").to_string_lossy().into_owned();
    let write = [
        "results-page",
        "--records",
        records.as_str(),
        "--out",
        page.as_str(),
        "--archive-out",
        archive.as_str(),
        "--embed-in",
        readme.as_str(),
    ];
    let check = [&write[..], &["--check"][..]].concat();
    // No page yet: the check names it.
    let (ok, stderr) = xtask(&check);
    assert!(
        !ok && error_line(&stderr).contains("results.md"),
        "{stderr}"
    );
    let (ok, stderr) = xtask(&write);
    assert!(ok, "{stderr}");
    let (ok, stderr) = xtask(&check);
    assert!(ok, "{stderr}");
    std::fs::write(d.join("results.md"), "edited by hand\n").unwrap();
    let (ok, stderr) = xtask(&check);
    let line = error_line(&stderr);
    assert!(
        !ok && line.contains("differs") && line.contains("results-page --records"),
        "{stderr}"
    );
    // The README's block was filled with the record's table, and an edit to it fails the check too.
    let (ok, stderr) = xtask(&write);
    assert!(ok, "{stderr}");
    let filled = std::fs::read_to_string(d.join("README.md")).unwrap();
    assert!(
        filled.contains("| what | record |\n|---|---|\n| x | [10.1](records/10-a.json#L2) |\n"),
        "{filled}"
    );
    std::fs::write(d.join("README.md"), filled.replace("| x |", "| y |")).unwrap();
    let (ok, stderr) = xtask(&check);
    assert!(!ok && error_line(&stderr).contains("README.md"), "{stderr}");
}
