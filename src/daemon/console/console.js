// boltwatch console: live updates (the pages are complete without this script).
// The page's event stream (body data-events) says when the structure changed; the page is
// then fetched again and its live part swapped in, at most one fetch at a time.
(function () {
  "use strict";
  var live = document.getElementById("live");
  var events = document.body.dataset.events;
  if (!live || !events || !window.EventSource) {
    return;
  }
  var busy = false;
  var again = false;
  function refresh() {
    if (busy) {
      again = true;
      return;
    }
    busy = true;
    fetch(location.href, { cache: "no-store", credentials: "same-origin" })
      .then(function (r) { return r.ok ? r.text() : null; })
      .then(function (html) {
        if (html === null) { return; }
        var next = new DOMParser().parseFromString(html, "text/html").getElementById("live");
        if (next) { live.innerHTML = next.innerHTML; }
        document.body.dataset.updated = String(Date.now());
      })
      .catch(function () { document.body.dataset.live = "fetch failed"; })
      .finally(function () {
        busy = false;
        if (again) {
          again = false;
          refresh();
        }
      });
  }
  var source = new EventSource(events);
  source.onopen = function () { document.body.dataset.live = "open"; };
  source.onerror = function () { document.body.dataset.live = "reconnecting"; };
  source.onmessage = refresh;
})();
