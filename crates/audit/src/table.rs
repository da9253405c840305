//! The residual table: one row per compared quantity (a pixel, a weighed object, …),
//! measured vs simulated value, whether the measurement is missing, the unit it
//! belongs to (a frame: the unit of the train/held-out split and of the significance
//! test) and the covariate columns the search may explain it with.
use recon_core::{Error, Result};
use std::collections::BTreeMap;
use std::path::Path;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ColumnKind {
    Numeric,
    /// Values are integer category codes (`group` form).
    Categorical,
}

#[derive(Clone, Debug)]
pub struct Column {
    pub name: String,
    pub kind: ColumnKind,
    pub values: Vec<f64>,
    /// Display names of categories (CSV text categories); code → label.
    pub labels: BTreeMap<i64, String>,
}

impl Column {
    pub fn numeric(name: &str, values: Vec<f64>) -> Self {
        Column { name: name.into(), kind: ColumnKind::Numeric, values, labels: BTreeMap::new() }
    }
    pub fn categorical(name: &str, values: Vec<f64>) -> Self {
        Column { name: name.into(), kind: ColumnKind::Categorical, values, labels: BTreeMap::new() }
    }
    pub fn label(&self, code: i64) -> String {
        self.labels.get(&code).cloned().unwrap_or_else(|| code.to_string())
    }
}

/// Measured vs simulated values with covariates. `measured` is NaN where the
/// measurement is missing (a depth hole). The `sd_floor`, `sd_offset` and
/// `p_offset` columns carry what the current sensor model already predicts for the
/// spread and the missing rate (see `audit::fit`); they are 0 for plain tables.
#[derive(Clone, Debug, Default)]
pub struct ResidualTable {
    /// Measured value per row (non-finite: missing).
    pub measured: Vec<f64>,
    /// Simulated value per row.
    pub simulated: Vec<f64>,
    /// Noise floor combined in quadrature with the fitted global noise (sensor base + quantisation).
    pub sd_floor: Vec<f64>,
    /// Spread already explained by the current model's noise effects (added).
    pub sd_offset: Vec<f64>,
    /// Lowest spread a row can show whatever the effects (the sensor's quantisation);
    /// empty = none. Negative noise terms stop here instead of at ~0, where a
    /// quantised residual would count as a wild outlier.
    pub sd_clamp: Vec<f64>,
    /// Missing rate already explained by the current model's dropout effects (added).
    pub p_offset: Vec<f64>,
    /// Unit (frame) index of each row, into `unit_names`.
    pub unit: Vec<usize>,
    /// Name of each unit (frame).
    pub unit_names: Vec<String>,
    /// Covariate columns.
    pub columns: Vec<Column>,
    /// Where the table came from (for error messages and the report).
    pub source: String,
    /// Unit of measured/simulated values, for display ("m" for depth).
    pub value_unit: String,
}

impl ResidualTable {
    /// Number of rows.
    pub fn len(&self) -> usize {
        self.measured.len()
    }
    /// Whether the table has no rows.
    pub fn is_empty(&self) -> bool {
        self.measured.is_empty()
    }
    /// Whether row `i`'s measurement is missing (non-finite).
    pub fn missing(&self, i: usize) -> bool {
        !self.measured[i].is_finite()
    }
    /// Measured minus simulated value of row `i`.
    pub fn residual(&self, i: usize) -> f64 {
        self.measured[i] - self.simulated[i]
    }
    /// Index of the column named `name`.
    pub fn column(&self, name: &str) -> Option<usize> {
        self.columns.iter().position(|c| c.name == name)
    }
    /// Number of units (frames).
    pub fn n_units(&self) -> usize {
        self.unit_names.len()
    }

    /// Consistent lengths, finite simulated values and covariates, units in range.
    pub fn validate(&self) -> Result<()> {
        let n = self.len();
        let bad = |msg: String| Err(Error::input(self.source.clone(), msg));
        for (name, len) in [
            ("simulated", self.simulated.len()),
            ("sd_floor", self.sd_floor.len()),
            ("sd_offset", self.sd_offset.len()),
            ("p_offset", self.p_offset.len()),
            ("unit", self.unit.len()),
        ] {
            if len != n {
                return bad(format!("column `{name}` has {len} rows, expected {n}"));
            }
        }
        if !self.sd_clamp.is_empty() && self.sd_clamp.len() != n {
            return bad(format!("column `sd_clamp` has {} rows, expected {n} (or none)", self.sd_clamp.len()));
        }
        if n == 0 {
            return bad("no rows to compare".into());
        }
        if let Some(i) = self.simulated.iter().position(|v| !v.is_finite()) {
            return bad(format!("row {i}: simulated value is not a finite number"));
        }
        if let Some(i) = self.unit.iter().position(|&u| u >= self.unit_names.len()) {
            return bad(format!("row {i}: unit index out of range"));
        }
        for c in &self.columns {
            if c.values.len() != n {
                return bad(format!("column `{}` has {} rows, expected {n}", c.name, c.values.len()));
            }
            if let Some(i) = c.values.iter().position(|v| !v.is_finite()) {
                return bad(format!("row {i}: column `{}` is not a finite number", c.name));
            }
        }
        Ok(())
    }

    /// Reads a CSV table (header row; comma separated; double quotes around fields
    /// that contain commas). `measured` and `simulated` name the compared columns;
    /// an empty, `NA` or `NaN` measured cell is a missing measurement. Rows whose
    /// simulated value or a covariate is empty are skipped (counted in the second
    /// return value). Text columns, and those named in `categorical`, are
    /// categorical; the others numeric. `unit` names the column whose values group
    /// rows into split units (default: `frame` if present, else each row is a unit).
    pub fn from_csv(
        path: &Path,
        measured: &str,
        simulated: &str,
        unit: Option<&str>,
        categorical: &[String],
        ignore: &[String],
    ) -> Result<(Self, usize)> {
        let file = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let mut lines = text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty());
        let (_, header) = lines.next().ok_or_else(|| Error::input(&file, "empty file: expected a header row"))?;
        let names: Vec<String> = split_csv_line(header).into_iter().map(|s| s.trim().to_string()).collect();
        let find = |col: &str, what: &str| {
            names
                .iter()
                .position(|n| n == col)
                .ok_or_else(|| Error::input(&file, format!("{what} column `{col}` not in the header (columns: {})", names.join(", "))))
        };
        let im = find(measured, "--measured")?;
        let is = find(simulated, "--simulated")?;
        let unit_col = match unit {
            Some(u) => Some(find(u, "--unit")?),
            None => names.iter().position(|n| n == "frame"),
        };
        for c in categorical.iter().chain(ignore) {
            find(c, "named")?;
        }
        let mut cells: Vec<Vec<String>> = Vec::new();
        for (ln, line) in lines {
            let f = split_csv_line(line);
            if f.len() != names.len() {
                return Err(Error::input(&file, format!("line {}: {} fields, the header has {}", ln + 1, f.len(), names.len())));
            }
            cells.push(f.into_iter().map(|s| s.trim().to_string()).collect());
        }
        if cells.is_empty() {
            return Err(Error::input(&file, "no data rows"));
        }
        let is_na = |s: &str| s.is_empty() || s.eq_ignore_ascii_case("na") || s.eq_ignore_ascii_case("nan");
        let cov_idx: Vec<usize> = (0..names.len()).filter(|&j| j != im && j != is && !ignore.contains(&names[j])).collect();
        // A covariate is numeric when every non-empty cell parses.
        let numeric: Vec<bool> = (0..names.len())
            .map(|j| {
                !categorical.contains(&names[j])
                    && cells.iter().all(|r| is_na(&r[j]) || r[j].parse::<f64>().map(|v| v.is_finite()).unwrap_or(false))
            })
            .collect();
        if !numeric[is] {
            return Err(Error::input(&file, format!("--simulated column `{simulated}` holds non-numeric values")));
        }
        if let Some((ln, _)) =
            cells.iter().enumerate().find(|(_, r)| !is_na(&r[im]) && r[im].parse::<f64>().map(|v| !v.is_finite()).unwrap_or(true))
        {
            return Err(Error::input(
                &file,
                format!("data row {}: --measured `{measured}` value `{}` is not a number (empty/NA = missing)", ln + 1, cells[ln][im]),
            ));
        }
        let mut keep = Vec::new();
        let mut skipped = 0;
        for (r, row) in cells.iter().enumerate() {
            if is_na(&row[is]) || cov_idx.iter().any(|&j| is_na(&row[j])) || unit_col.is_some_and(|u| is_na(&row[u])) {
                skipped += 1;
            } else {
                keep.push(r);
            }
        }
        if keep.is_empty() {
            return Err(Error::input(&file, "every row lacks the simulated value or a covariate"));
        }
        let mut t = ResidualTable { source: file.clone(), ..Default::default() };
        for &r in &keep {
            let m = &cells[r][im];
            t.measured.push(if is_na(m) { f64::NAN } else { m.parse().unwrap_or(f64::NAN) });
            t.simulated.push(cells[r][is].parse().unwrap_or(f64::NAN));
        }
        let n = keep.len();
        t.sd_floor = vec![0.0; n];
        t.sd_offset = vec![0.0; n];
        t.p_offset = vec![0.0; n];
        match unit_col {
            Some(u) => {
                let mut ids: BTreeMap<String, usize> = BTreeMap::new();
                for &r in &keep {
                    let k = cells[r][u].clone();
                    let next = ids.len();
                    ids.entry(k).or_insert(next);
                }
                // Stable order: by name (numerically when numeric).
                let mut names_sorted: Vec<String> = ids.keys().cloned().collect();
                names_sorted.sort_by(|a, b| match (a.parse::<f64>(), b.parse::<f64>()) {
                    (Ok(x), Ok(y)) => x.total_cmp(&y),
                    _ => a.cmp(b),
                });
                let index: BTreeMap<&String, usize> = names_sorted.iter().enumerate().map(|(i, s)| (s, i)).collect();
                t.unit = keep.iter().map(|&r| index[&cells[r][u]]).collect();
                t.unit_names = names_sorted.clone();
            }
            None => {
                t.unit = (0..n).collect();
                t.unit_names = keep.iter().map(|r| format!("row {}", r + 1)).collect();
            }
        }
        for &j in &cov_idx {
            if numeric[j] {
                t.columns.push(Column::numeric(&names[j], keep.iter().map(|&r| cells[r][j].parse().unwrap_or(f64::NAN)).collect()));
            } else {
                // Text (or forced) categories: integer codes in order of first appearance;
                // integer-valued cells keep their own value as the code.
                let all_int = keep.iter().all(|&r| cells[r][j].parse::<i64>().is_ok());
                let mut codes: BTreeMap<String, i64> = BTreeMap::new();
                let mut col = Column::categorical(&names[j], Vec::with_capacity(n));
                for &r in &keep {
                    let s = &cells[r][j];
                    let code = if all_int {
                        s.parse::<i64>().unwrap_or(0)
                    } else {
                        let next = codes.len() as i64;
                        *codes.entry(s.clone()).or_insert(next)
                    };
                    col.labels.insert(code, s.clone());
                    col.values.push(code as f64);
                }
                t.columns.push(col);
            }
        }
        t.validate()?;
        Ok((t, skipped))
    }
}

/// Splits one CSV line; double quotes protect commas, `""` is a literal quote.
fn split_csv_line(line: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut cur = String::new();
    let mut quoted = false;
    let mut chars = line.chars().peekable();
    while let Some(c) = chars.next() {
        match (c, quoted) {
            ('"', true) if chars.peek() == Some(&'"') => {
                cur.push('"');
                chars.next();
            }
            ('"', _) => quoted = !quoted,
            (',', false) => out.push(std::mem::take(&mut cur)),
            _ => cur.push(c),
        }
    }
    out.push(cur);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_csv_with_categories_missing_and_units() {
        let dir = recon_testkit::tmp("audit-csv");
        let p = dir.join("t.csv");
        std::fs::write(
            &p,
            "frame,measured,sim,material,temp\n0,1.0,1.1,\"wood, oak\",20\n0,NA,2.0,steel,21\n1,3.0,2.9,wood,\n2,4.5,4.0,steel,22\n",
        )
        .unwrap();
        let (t, skipped) = ResidualTable::from_csv(&p, "measured", "sim", None, &[], &[]).unwrap();
        assert_eq!(skipped, 1, "row with an empty covariate is skipped");
        assert_eq!(t.len(), 3);
        assert!(t.missing(1) && !t.missing(0));
        assert_eq!(t.unit, vec![0, 0, 1]);
        assert_eq!(t.unit_names, vec!["0", "2"]);
        let m = &t.columns[t.column("material").unwrap()];
        assert_eq!(m.kind, ColumnKind::Categorical);
        assert_eq!(m.label(m.values[0] as i64), "wood, oak");
        assert_eq!(t.columns[t.column("temp").unwrap()].kind, ColumnKind::Numeric);
        assert!(t.column("frame").is_some(), "the unit column stays a covariate");
        // Errors name the file and what is wrong.
        let e = ResidualTable::from_csv(&p, "nope", "sim", None, &[], &[]).unwrap_err().to_string();
        assert!(e.contains("t.csv") && e.contains("--measured") && e.contains("nope"), "{e}");
        std::fs::write(&p, "a,b\n1,x\n").unwrap();
        let e = ResidualTable::from_csv(&p, "a", "b", None, &[], &[]).unwrap_err().to_string();
        assert!(e.contains("non-numeric"), "{e}");
        std::fs::write(&p, "a,b\n1\n").unwrap();
        let e = ResidualTable::from_csv(&p, "a", "b", None, &[], &[]).unwrap_err().to_string();
        assert!(e.contains("line 2") && e.contains("1 fields"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
