//! Reports: one small document model, written both as a
//! self-contained HTML page (images embedded as `data:` URIs, opens in a
//! browser with no server) and as Markdown (images linked by relative path).
//!
//! `compare`, `experiments` and the demo build a `Vec<Block>` and call
//! [`write_report`]; neither writer knows what the blocks mean.

use crate::error::{Error, Result};
use base64::Engine as _;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// One block of a report.
#[derive(Clone, Debug)]
pub enum Block {
    /// A heading of level 1–4.
    Heading(u8, String),
    /// A paragraph (plain text; `code` spans in backticks are kept).
    Para(String),
    /// A preformatted block (commands).
    Code(String),
    /// A table: header and rows of cells (plain text).
    Table {
        header: Vec<String>,
        rows: Vec<Vec<String>>,
    },
    /// Images in aligned columns: rows of cells, each an image with its
    /// caption or empty (`None`), each image `width` CSS pixels wide
    /// (pixelated scaling) in HTML. Paths are files on disk.
    Grid {
        rows: Vec<Vec<Option<(String, PathBuf)>>>,
        width: u32,
    },
    /// One wide figure (a plot or a contact sheet).
    Figure { caption: String, path: PathBuf },
}

impl Block {
    /// A table with a header of string literals.
    pub fn table(header: &[&str], rows: Vec<Vec<String>>) -> Block {
        Block::Table {
            header: header.iter().map(|h| h.to_string()).collect(),
            rows,
        }
    }
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// Inline `code` spans of escaped text.
fn inline(s: &str) -> String {
    let mut out = String::new();
    for (k, part) in escape(s).split('`').enumerate() {
        if k % 2 == 1 {
            let _ = write!(out, "<code>{part}</code>");
        } else {
            out.push_str(part);
        }
    }
    out
}

/// A `data:` URI of an image file (PNG or SVG by extension).
fn data_uri(path: &Path) -> Result<String> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let mime = match path.extension().and_then(|e| e.to_str()) {
        Some("svg") => "image/svg+xml",
        _ => "image/png",
    };
    Ok(format!(
        "data:{mime};base64,{}",
        base64::engine::general_purpose::STANDARD.encode(bytes)
    ))
}

const STYLE: &str = "body{font-family:system-ui,sans-serif;max-width:1200px;margin:2em auto;\
padding:0 1em;color:#222}table{border-collapse:collapse;margin:.5em 0 1.5em}\
td,th{border:1px solid #ccc;padding:.25em .6em;text-align:left}\
th{background:#f3f3f3}td.n{text-align:right}\
figure{display:inline-block;margin:0 6px 6px 0;text-align:center;font-size:.85em}\
table.grid{border-collapse:separate;margin:0 0 .5em}table.grid td{border:none;padding:0 6px 0 0;\
vertical-align:top}table.grid figure{margin:0}img.tile{image-rendering:pixelated;outline:1px solid #ccc}pre{background:#f6f6f6;padding:.6em;overflow-x:auto}\
code{background:#f3f3f3;padding:0 .2em}";

/// The blocks as one self-contained HTML page.
pub fn to_html(title: &str, blocks: &[Block]) -> Result<String> {
    let mut h = format!(
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\
         <title>{0}</title><style>{STYLE}</style></head><body>\n<h1>{0}</h1>\n",
        escape(title)
    );
    for b in blocks {
        match b {
            Block::Heading(level, text) => {
                let _ = writeln!(h, "<h{level}>{}</h{level}>", inline(text));
            }
            Block::Para(text) => {
                let _ = writeln!(h, "<p>{}</p>", inline(text));
            }
            Block::Code(text) => {
                let _ = writeln!(h, "<pre>{}</pre>", escape(text));
            }
            Block::Table { header, rows } => {
                h.push_str("<table><tr>");
                for c in header {
                    let _ = write!(h, "<th>{}</th>", inline(c));
                }
                h.push_str("</tr>\n");
                for r in rows {
                    h.push_str("<tr>");
                    for c in r {
                        let class = if numeric(c) { " class=\"n\"" } else { "" };
                        let _ = write!(h, "<td{class}>{}</td>", inline(c));
                    }
                    h.push_str("</tr>\n");
                }
                h.push_str("</table>\n");
            }
            Block::Grid { rows, width } => {
                h.push_str("<table class=\"grid\">");
                for row in rows {
                    h.push_str("<tr>");
                    for cell in row {
                        let _ = write!(h, "<td style=\"width:{width}px\">");
                        if let Some((caption, path)) = cell {
                            let _ = write!(
                                h,
                                "<figure><img class=\"tile\" width=\"{width}\" src=\"{}\" \
                                 alt=\"{}\"><figcaption>{}</figcaption></figure>",
                                data_uri(path)?,
                                escape(caption),
                                inline(caption)
                            );
                        }
                        h.push_str("</td>");
                    }
                    h.push_str("</tr>\n");
                }
                h.push_str("</table>\n");
            }
            Block::Figure { caption, path } => {
                let _ = writeln!(
                    h,
                    "<figure><img src=\"{}\" alt=\"{}\" style=\"max-width:100%\">\
                     <figcaption>{}</figcaption></figure>",
                    data_uri(path)?,
                    escape(caption),
                    inline(caption)
                );
            }
        }
    }
    h.push_str("</body></html>\n");
    Ok(h)
}

/// `path` relative to `base` where it lies below it (Markdown links).
fn relative(path: &Path, base: &Path) -> String {
    path.strip_prefix(base)
        .unwrap_or(path)
        .to_string_lossy()
        .into_owned()
}

/// The blocks as Markdown; image links relative to `base` (the directory
/// the Markdown file is written to).
pub fn to_markdown(title: &str, blocks: &[Block], base: &Path) -> String {
    let mut m = format!("# {title}\n\n");
    let cells = |r: &[String]| format!("| {} |\n", r.join(" | ").replace('\n', " "));
    for b in blocks {
        match b {
            Block::Heading(level, text) => {
                let _ = writeln!(m, "{} {text}\n", "#".repeat(*level as usize));
            }
            Block::Para(text) => {
                let _ = writeln!(m, "{text}\n");
            }
            Block::Code(text) => {
                let _ = writeln!(m, "```\n{text}\n```\n");
            }
            Block::Table { header, rows } => {
                m.push_str(&cells(header));
                let rule: Vec<String> = (0..header.len())
                    .map(|k| {
                        let num = rows.first().is_some_and(|r| numeric(&r[k]));
                        if num { "--:" } else { ":--" }.to_string()
                    })
                    .collect();
                m.push_str(&cells(&rule));
                for r in rows {
                    m.push_str(&cells(r));
                }
                m.push('\n');
            }
            Block::Grid { rows, .. } => {
                // Each grid row as a row of captions over a row of images;
                // the first row's captions are the table's header.
                for (k, row) in rows.iter().enumerate() {
                    let captions: Vec<String> = row
                        .iter()
                        .map(|c| c.as_ref().map_or(String::new(), |(c, _)| c.clone()))
                        .collect();
                    m.push_str(&cells(&captions));
                    if k == 0 {
                        m.push_str(&cells(&vec![":-:".to_string(); row.len()]));
                    }
                    let imgs: Vec<String> = row
                        .iter()
                        .map(|c| {
                            c.as_ref().map_or(String::new(), |(c, p)| {
                                format!("![{c}]({})", relative(p, base))
                            })
                        })
                        .collect();
                    m.push_str(&cells(&imgs));
                }
                m.push('\n');
            }
            Block::Figure { caption, path } => {
                let _ = writeln!(m, "![{caption}]({})\n\n*{caption}*\n", relative(path, base));
            }
        }
    }
    m
}

/// The blocks as plain text for a terminal: headings, paragraphs and tables
/// in aligned columns (numbers right-aligned); code, images and figures are
/// left out.
pub fn to_text(blocks: &[Block]) -> String {
    let mut t = String::new();
    for b in blocks {
        match b {
            Block::Heading(level, text) => {
                if !t.is_empty() {
                    t.push('\n');
                }
                let _ = writeln!(t, "{} {text}", "#".repeat(*level as usize));
            }
            Block::Para(text) => {
                let _ = writeln!(t, "{text}");
            }
            Block::Table { header, rows } => {
                let width = |k: usize| {
                    std::iter::once(header)
                        .chain(rows)
                        .filter_map(|r| r.get(k))
                        .map(|c| c.chars().count())
                        .max()
                        .unwrap_or(0)
                };
                let widths: Vec<usize> = (0..header.len()).map(width).collect();
                for (n, r) in std::iter::once(header).chain(rows).enumerate() {
                    let cells: Vec<String> = r
                        .iter()
                        .zip(&widths)
                        .map(|(c, &w)| {
                            let pad = " ".repeat(w.saturating_sub(c.chars().count()));
                            if n > 0 && numeric(c) {
                                format!("{pad}{c}")
                            } else {
                                format!("{c}{pad}")
                            }
                        })
                        .collect();
                    let _ = writeln!(t, "  {}", cells.join("  ").trim_end());
                }
            }
            Block::Code(_) | Block::Grid { .. } | Block::Figure { .. } => {}
        }
    }
    t
}

/// Writes `<dir>/<stem>.html` (self-contained) and `<dir>/<stem>.md`,
/// atomically; returns the HTML path.
pub fn write_report(dir: &Path, stem: &str, title: &str, blocks: &[Block]) -> Result<PathBuf> {
    let html = dir.join(format!("{stem}.html"));
    crate::jobs::store::write_atomic(&html, to_html(title, blocks)?.as_bytes())?;
    crate::jobs::store::write_atomic(
        &dir.join(format!("{stem}.md")),
        to_markdown(title, blocks, dir).as_bytes(),
    )?;
    Ok(html)
}

/// A number with 4 significant figures for a table cell ("—" if absent or
/// not finite).
pub fn num(v: Option<f64>) -> String {
    match v {
        Some(v) if v.is_finite() => {
            if v != 0.0 && (v.abs() < 1e-3 || v.abs() >= 1e5) {
                format!("{v:.3e}")
            } else {
                format!("{v:.4}")
            }
        }
        _ => "—".into(),
    }
}

/// True for a cell that reads as a number (right-aligned in tables).
fn numeric(cell: &str) -> bool {
    cell.starts_with(|c: char| c.is_ascii_digit() || "+-−<—".contains(c))
}

/// A noise-subtracted relative error of resolution `resolution`
/// ([`super::render::resolution`]): a percentage where it is resolved,
/// else "< x" with x its upper bound ([`super::render::error_bound`]);
/// "< noise" for an error of 0 without a resolution.
pub fn err(v: Option<f64>, resolution: f64) -> String {
    match v {
        Some(e) if e.is_finite() && e < resolution => {
            format!("< {}", pct(Some(super::render::error_bound(e, resolution))))
        }
        Some(0.0) => "< noise".into(),
        v => pct(v),
    }
}

/// A percentage with one decimal ("—" if absent).
pub fn pct(v: Option<f64>) -> String {
    match v {
        Some(v) if v.is_finite() => format!("{:.1} %", 100.0 * v),
        _ => "—".into(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn html_is_self_contained_and_markdown_links_relative() {
        let dir = std::env::temp_dir().join(format!("svk-report-{}", std::process::id()));
        std::fs::create_dir_all(dir.join("sub")).unwrap();
        let png = dir.join("sub/a.png");
        crate::jobs::output::write_png_bytes(&png, 1, true, &[255, 0, 0]).unwrap();
        let blocks = vec![
            Block::Heading(2, "Errors <&>".into()),
            Block::Table {
                header: vec!["method".into(), "rel RMSE".into()],
                rows: vec![vec!["`learned`".into(), pct(Some(0.0342))]],
            },
            Block::Grid {
                rows: vec![
                    vec![Some(("reference".into(), png.clone())), None],
                    vec![None, Some(("again".into(), png.clone()))],
                ],
                width: 64,
            },
        ];
        let html = write_report(&dir, "r", "T", &blocks).unwrap();
        let h = std::fs::read_to_string(html).unwrap();
        assert!(h.contains("data:image/png;base64,iVBOR"), "PNG embedded");
        assert!(h.contains("<title>T</title>") && h.contains("<h1>T</h1>"));
        assert!(!h.contains("sub/a.png"), "no file links in HTML");
        assert!(h.contains("Errors &lt;&amp;&gt;") && h.contains("<code>learned</code>"));
        assert!(h.contains("3.4 %"));
        // The grid's columns line up: an empty cell keeps its place.
        assert!(h.contains("<tr><td style=\"width:64px\"></td><td"), "{h}");
        let md = std::fs::read_to_string(dir.join("r.md")).unwrap();
        assert!(md.contains("| ![reference](sub/a.png) |  |"), "{md}");
        assert!(
            md.contains("|  | again |\n|  | ![again](sub/a.png) |"),
            "{md}"
        );
        assert!(md.contains("| `learned` | 3.4 % |"), "{md}");
        assert!(
            md.contains("| :-- | --: |"),
            "text left, numbers right: {md}"
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
