// Swagger UI on this service's OpenAPI document. A file, not an inline script, so that the
// page's Content-Security-Policy (scripts from this origin only) holds for /docs too.
window.addEventListener("load", () => {
  window.ui = SwaggerUIBundle({
    url: "/openapi.json",
    dom_id: "#swagger-ui",
    layout: "BaseLayout",
    deepLinking: true,
    showExtensions: true,
    showCommonExtensions: true,
    presets: [SwaggerUIBundle.presets.apis, SwaggerUIBundle.SwaggerUIStandalonePreset],
    validatorUrl: null, // the default sends the document's URL to validator.swagger.io
  });
});
