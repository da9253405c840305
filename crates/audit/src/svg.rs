//! SVG primitives shared by the report's plots and the HTML page: the plot frame and escaping.

/// Text escaped for HTML and SVG content and attributes.
pub(crate) fn esc(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;")
}

/// The 640×400 plot area of the audit's SVG plots, mapping data to pixels.
pub(crate) struct PlotArea {
    pub x0: f64,
    pub x1: f64,
    pub y0: f64,
    pub y1: f64,
}

const PLOT: (f64, f64, f64, f64, f64, f64) = (640.0, 400.0, 70.0, 20.0, 40.0, 50.0);

impl PlotArea {
    pub fn sx(&self, x: f64) -> f64 {
        let (w, _, ml, mr, _, _) = PLOT;
        ml + (x - self.x0) / (self.x1 - self.x0) * (w - ml - mr)
    }
    pub fn sy(&self, y: f64) -> f64 {
        let (_, h, _, _, mt, mb) = PLOT;
        let ph = h - mt - mb;
        mt + ph - (y.clamp(self.y0, self.y1) - self.y0) / (self.y1 - self.y0) * ph
    }
    /// The SVG's opening: background, title, frame, 5 ticks per axis and the axis labels
    /// (texts already escaped).
    pub fn open(&self, title: &str, xlabel: &str, ylabel: &str) -> String {
        let (w, h, ml, mr, mt, mb) = PLOT;
        let (pw, ph) = (w - ml - mr, h - mt - mb);
        let mut s = format!("<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{h}\" font-family=\"sans-serif\" font-size=\"12\">\n<rect width=\"100%\" height=\"100%\" fill=\"white\"/>\n");
        s += &format!("<text x=\"{}\" y=\"20\" text-anchor=\"middle\" font-size=\"14\">{title}</text>\n", w / 2.0);
        s += &format!("<rect x=\"{ml}\" y=\"{mt}\" width=\"{pw}\" height=\"{ph}\" fill=\"none\" stroke=\"black\"/>\n");
        for i in 0..=4 {
            let x = self.x0 + (self.x1 - self.x0) * i as f64 / 4.0;
            let y = self.y0 + (self.y1 - self.y0) * i as f64 / 4.0;
            s += &format!("<text x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"middle\">{}</text>\n", self.sx(x), mt + ph + 16.0, tick(x));
            s += &format!("<text x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"end\">{}</text>\n", ml - 5.0, self.sy(y) + 4.0, tick(y));
        }
        s += &format!("<text x=\"{}\" y=\"{}\" text-anchor=\"middle\">{xlabel}</text>\n", ml + pw / 2.0, h - 12.0);
        s += &format!(
            "<text x=\"16\" y=\"{}\" text-anchor=\"middle\" transform=\"rotate(-90 16 {})\">{ylabel}</text>\n",
            mt + ph / 2.0,
            mt + ph / 2.0
        );
        s
    }
}

pub(crate) fn tick(x: f64) -> String {
    if x != 0.0 && (x.abs() >= 1e4 || x.abs() < 1e-2) {
        format!("{x:.2e}")
    } else {
        format!("{x:.2}")
    }
}
