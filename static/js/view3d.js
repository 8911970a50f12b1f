// The 3-D view: the viser viewer relayed under /viser/, in an iframe (token in the query).

import { $, withToken } from "./api.js";

export function setupView3d() {
  $("viewer3d").src = withToken("/viser/");
  $("open3d").href = withToken("/viser/");
}
