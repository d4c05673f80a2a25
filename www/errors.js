// Every uncaught error, unhandled rejection and console.error of the page, in order; join.js and the console
// show nothing of these by design, the end-to-end tests read them through WebDriver.
window.__pageErrors = [];
window.addEventListener("error", (e) => window.__pageErrors.push(String(e.message || e)));
window.addEventListener("unhandledrejection", (e) => window.__pageErrors.push("unhandled rejection: " + String(e.reason)));
(() => {
  const original = console.error.bind(console);
  console.error = (...args) => {
    window.__pageErrors.push(args.map(String).join(" "));
    original(...args);
  };
})();
